"""The import graph: the engine (``clsplat/``) imports nothing from the model families or the
benchmarks, at module level or lazily, and no project modules import each other in a cycle.

Read from the source with ``ast`` (every ``import``, inside functions too, and literal
``importlib.import_module`` names), and checked once more at run time in a fresh interpreter
that imports every engine module. Every package folder is also listed in setup.cfg's
``packages`` (a package missing there is silently left out of the wheel)."""
from __future__ import annotations

import ast
import configparser
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: source folder -> installed package (setup.cfg's package_dir)
PACKAGES = {"clsplat": "clsplat", "kernels": "clsplat.kernels", "bench": "clsplat.bench",
            "models": "clsplat.models"}
UPWARD = ("clsplat.models", "clsplat.bench")


def _modules() -> dict[str, Path]:
    mods = {}
    for folder, pkg in PACKAGES.items():
        for f in (ROOT / folder).rglob("*.py"):
            rel = f.relative_to(ROOT / folder)
            if rel.parts[0] == "experiments":      # scripts, not installed
                continue
            parts = list(rel.with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join([pkg, *parts])] = f
    return mods


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Project modules that ``name`` imports (the deepest module each statement names)."""
    is_pkg = path.name == "__init__.py"
    base = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()

    def resolve(mod: str, names=()):
        cands = [f"{mod}.{n}" for n in names if f"{mod}.{n}" in known]
        if cands:
            out.update(cands)
        elif mod in known:
            out.add(mod)

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                resolve(a.name)
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                up = base.split(".")
                up = up[:len(up) - (node.level - 1)]
                mod = ".".join(up + ([mod] if mod else []))
            resolve(mod, [a.name for a in node.names])
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
              and node.args and isinstance(node.args[0], (ast.Constant, ast.JoinedStr))):
            arg = node.args[0]
            text = arg.value if isinstance(arg, ast.Constant) else "".join(
                v.value if isinstance(v, ast.Constant) else "{}" for v in arg.values)
            prefix = text.split("{")[0].rstrip(".")
            if prefix.startswith(UPWARD) or prefix in UPWARD:
                out.add(prefix)             # names a model/bench module by a computed name
            else:
                resolve(prefix)
    out.discard(name)
    return out


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: _imports(m, p, set(mods)) for m, p in mods.items()}


def test_engine_imports_nothing_above_it():
    bad = {m: sorted(d for d in deps if d.startswith(UPWARD))
           for m, deps in _graph().items()
           if not m.startswith(UPWARD)}
    bad = {m: d for m, d in bad.items() if d}
    assert not bad, f"the engine imports models/bench: {bad}"


def test_no_production_module_imports_the_float64_reference():
    """clsplat.reference is the tests' oracle: the engine and the model families take what they
    share with it (the SH basis, clsplat/sh.py) from the engine's own modules. The benchmarks may
    measure against it."""
    bad = sorted(m for m, deps in _graph().items()
                 if "clsplat.reference" in deps and not m.startswith("clsplat.bench"))
    assert not bad, f"production modules import the test oracle clsplat.reference: {bad}"


def test_no_import_cycles():
    g = _graph()
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def strong(v):                                   # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in g:
        if v not in index:
            strong(v)
    assert not cycles, f"modules that import each other: {cycles}"


@pytest.mark.slow   # spawns an interpreter that imports every engine module
def test_importing_every_engine_module_loads_no_model_or_benchmark():
    engine = sorted(m for m in _modules() if not m.startswith(UPWARD))
    code = textwrap.dedent(f"""
        import importlib, sys
        for m in {engine!r}:
            importlib.import_module(m)
        import clsplat.cli
        clsplat.cli.registered_commands()          # finding commands must not import them
        up = sorted(m for m in sys.modules if m.startswith({UPWARD!r}))
        print(up)
        sys.exit(1 if up else 0)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_graph_reader_sees_lazy_and_computed_imports(tmp_path):
    """The static check would catch the patterns the engine used to have (a lazy import inside a
    function, a relative one, an import_module with a computed model name)."""
    f = tmp_path / "cli.py"
    f.write_text(textwrap.dedent("""
        def a():
            from .models.autosplat.demo import run_demo
        def b(name):
            import importlib
            return importlib.import_module(f"clsplat.bench.{name}")
    """))
    known = {"clsplat", "clsplat.cli", "clsplat.models.autosplat.demo", "clsplat.bench.stages"}
    assert _imports("clsplat.cli", f, known) == {"clsplat.models.autosplat.demo", "clsplat.bench"}


def test_every_package_folder_is_in_setup_cfg():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    listed = set(cfg["options"]["packages"].split())
    folders = {m for m, p in _modules().items() if p.name == "__init__.py"}
    assert folders <= listed, f"package folders missing from setup.cfg [options] packages: {sorted(folders - listed)}"
    assert listed <= folders, f"setup.cfg lists packages with no folder: {sorted(listed - folders)}"


def test_every_package_data_pattern_in_setup_cfg_matches_a_file():
    """A package_data glob that matches nothing (``*.cl`` for ``clsplat.bench``, which has none)
    is a stale entry: the wheel would silently ship without what it names."""
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    stale = []
    for pkg, globs in cfg["options.package_data"].items():
        # the source folder: the longest installed package name that prefixes pkg, then the rest
        src, inst = max(((s, p) for s, p in PACKAGES.items() if pkg == p or pkg.startswith(p + ".")),
                        key=lambda sp: len(sp[1]))
        base = ROOT.joinpath(src, *pkg[len(inst):].split(".")[1:])
        stale += [f"{pkg} = {g}" for g in (x.strip() for x in globs.split(",")) if g and not any(base.glob(g))]
    assert not stale, f"setup.cfg package_data entries that match no file: {stale}"
