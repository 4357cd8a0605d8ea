"""The test tiers (setup.cfg's markers, the Makefile's ``check`` and ``test``): a test that starts
another Python interpreter (``sys.executable``: torchrun, kill-and-resume children, a foreign
device, Oclgrind cases) or a browser carries the ``slow`` marker, so ``make check`` (``-m "not
slow"``) stays quick as tests are added.

Read from the source with ``ast``: a test spawns when its body, a module-level helper it calls or
a module fixture it takes does, transitively within its file."""
from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent
#: tests that start an interpreter and stay in the quick tier, with the reason
QUICK_SPAWNS = {
    "test_threads.py::test_busy_cores_sees_a_competing_process": "a bare busy loop (no torch), 0.3 s",
}


def _spawns_here(node: ast.AST) -> bool:
    for n in ast.walk(node):
        if isinstance(n, ast.Attribute) and n.attr == "executable" and getattr(n.value, "id", "") == "sys":
            return True
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "HeadlessChromium":
            return True
    return False


def _is_slow(node: ast.AST) -> bool:
    """``pytest.mark.slow`` (or ``[..., pytest.mark.slow]``) anywhere in an expression."""
    return any(isinstance(n, ast.Attribute) and n.attr == "slow" and getattr(n.value, "attr", "") == "mark"
               for n in ast.walk(node))


def spawning_tests_without_the_marker(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    funcs = {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    module_slow = any(isinstance(n, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in n.targets)
                      and _is_slow(n.value) for n in tree.body)
    spawning = {name for name, f in funcs.items() if _spawns_here(f)}
    while True:    # helpers called and fixtures taken, to a fixed point
        more = set()
        for name, f in funcs.items():
            called = {getattr(c.func, "id", "") for c in ast.walk(f) if isinstance(c, ast.Call)}
            taken = {a.arg for a in f.args.args}
            if name not in spawning and (called | taken) & spawning:
                more.add(name)
        if not more:
            break
        spawning |= more
    bad = []
    for name in sorted(spawning):
        f = funcs[name]
        key = f"{path.name}::{name}"
        if name.startswith("test") and not module_slow and not any(_is_slow(d) for d in f.decorator_list) \
                and key not in QUICK_SPAWNS:
            bad.append(key)
    return bad


def test_every_test_that_starts_an_interpreter_or_a_browser_is_slow():
    bad = [k for p in sorted(TESTS.glob("test_*.py")) for k in spawning_tests_without_the_marker(p)]
    assert not bad, f"start interpreters or a browser but lack @pytest.mark.slow (make check runs them): {bad}"


def test_the_reader_follows_helpers_and_fixtures(tmp_path):
    f = tmp_path / "test_x.py"
    f.write_text('''
import subprocess, sys
import pytest

def _child():
    return subprocess.run([sys.executable, "-c", "pass"])

@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return _child()

def test_direct():
    _child()

def test_by_fixture(run):
    pass

@pytest.mark.slow
@pytest.mark.parametrize("x", [1])
def test_marked(run, x):
    pass

def test_quick():
    pass
''')
    assert spawning_tests_without_the_marker(f) == ["test_x.py::test_by_fixture", "test_x.py::test_direct"]
    f.write_text("import pytest\npytestmark = [pytest.mark.oclgrind, pytest.mark.slow]\n" + f.read_text())
    assert spawning_tests_without_the_marker(f) == []


def test_make_test_groups_each_module_and_each_shared_run_on_one_worker():
    """``make test`` runs ``--dist loadgroup``: conftest's hook gives every test of a module one
    xdist group (its module fixtures are built once) and merges the modules that take the same
    session-trained run (it is trained once), slow groups first."""
    import importlib.util
    import types

    spec = importlib.util.spec_from_file_location("tiers_conftest", TESTS / "conftest.py")
    conftest = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conftest)

    class Item:
        def __init__(self, nodeid, fixtures=(), slow=False):
            self.nodeid, self.fixturenames, self.slow, self.marks = nodeid, list(fixtures), slow, []

        def get_closest_marker(self, name):
            return object() if name == "slow" and self.slow else None

        def add_marker(self, mark):
            self.marks.append(mark)

    config = types.SimpleNamespace(pluginmanager=types.SimpleNamespace(hasplugin=lambda name: True),
                                   getoption=lambda name, default=None: "loadgroup")
    items = [Item("tests/test_a.py::t1"), Item("tests/test_a.py::t2"),
             Item("tests/test_b.py::t1", ["df_tiny_run"], slow=True), Item("tests/test_c.py::t1"),
             Item("tests/test_d.py::t1", ["df_tiny_run"]), Item("tests/test_d.py::t2")]
    conftest.pytest_collection_modifyitems(config, items)
    group = {i.nodeid: i.marks[0].args[0] for i in items}
    assert group["tests/test_a.py::t1"] == group["tests/test_a.py::t2"] != group["tests/test_c.py::t1"]
    assert group["tests/test_b.py::t1"] == group["tests/test_d.py::t1"] == group["tests/test_d.py::t2"]
    assert items[0].nodeid.startswith(("tests/test_b.py", "tests/test_d.py"))     # the slow group first
    assert len({i.nodeid for i in items}) == 6
    plain = [Item("tests/test_a.py::t1")]
    conftest.pytest_collection_modifyitems(types.SimpleNamespace(
        pluginmanager=config.pluginmanager, getoption=lambda name, default=None: "no"), plain)
    assert plain[0].marks == []                       # without --dist loadgroup nothing changes
