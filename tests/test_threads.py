"""clsplat.threads: the OpenMP spin and torch allocator settings set once at import, before torch
loads, and the default thread count from the cores other processes leave idle."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from clsplat.threads import OPT_OUT_ENV, THREAD_DEFAULTS, apply_thread_defaults

# The documented way: import clsplat before torch. The child reports its own environment,
# whether clsplat judged the defaults active, and what a grandchild process inherits.
_CHILD = """
import json, os, subprocess, sys
import clsplat, torch
from clsplat.threads import thread_defaults_active
grand = subprocess.run([sys.executable, "-c", "import os, json; print(json.dumps({k: os.environ.get(k) for k in %r}))"],
                       capture_output=True, text=True, check=True).stdout
# torch's allocator with THP_MEM_ALLOC_ENABLE page-aligns allocations of 2 MB and more (else 64 B
# past a page: glibc's chunk header)
big = [torch.empty((3 << 20) + 4096 * i, dtype=torch.uint8) for i in range(4)]
print(json.dumps({"env": {k: os.environ.get(k) for k in %r}, "active": thread_defaults_active(),
                  "grandchild": json.loads(grand), "page_aligned": [t.data_ptr() %% 4096 == 0 for t in big]}))
""" % (sorted(THREAD_DEFAULTS), sorted(THREAD_DEFAULTS))


def _child(**env) -> dict:
    base = {k: v for k, v in os.environ.items()
            if k not in THREAD_DEFAULTS and k not in (OPT_OUT_ENV, "OMP_WAIT_POLICY")}
    r = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, timeout=120,
                       env={**base, **env})
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow   # spawns an interpreter that imports torch
def test_child_importing_clsplat_first_gets_the_defaults():
    got = _child()
    assert got["env"] == THREAD_DEFAULTS
    assert got["grandchild"] == THREAD_DEFAULTS  # inherited by processes it starts
    assert got["active"] is True
    assert all(got["page_aligned"])              # torch read the allocator setting: set before it loaded


@pytest.mark.slow   # spawns an interpreter that imports torch
def test_opt_out_leaves_the_environment_alone():
    got = _child(**{OPT_OUT_ENV: "0"})
    assert got["env"] == {k: None for k in THREAD_DEFAULTS}
    assert got["active"] is False
    assert not all(got["page_aligned"])          # torch's own 64-byte alignment


@pytest.mark.slow   # spawns an interpreter that imports torch
def test_user_values_win():
    got = _child(GOMP_SPINCOUNT="300000")  # libgomp's own default: long spins
    assert got["env"]["GOMP_SPINCOUNT"] == "300000"
    assert got["env"]["KMP_BLOCKTIME"] == THREAD_DEFAULTS["KMP_BLOCKTIME"]
    assert got["active"] is False  # spinning workers: the single-thread default stays


@pytest.mark.slow   # spawns an interpreter that imports torch
def test_a_users_wait_policy_keeps_its_spin_count():
    """libgomp lets GOMP_SPINCOUNT override OMP_WAIT_POLICY: setting it beside a user's
    policy would silently change what the user chose."""
    active = _child(OMP_WAIT_POLICY="ACTIVE")
    assert active["env"]["GOMP_SPINCOUNT"] is None and active["active"] is False
    passive = _child(OMP_WAIT_POLICY="PASSIVE")
    assert passive["env"]["GOMP_SPINCOUNT"] is None and passive["active"] is True


def test_apply_sets_only_what_is_unset():
    env = {"KMP_BLOCKTIME": "200", "THP_MEM_ALLOC_ENABLE": "0"}
    assert apply_thread_defaults(env) == {"GOMP_SPINCOUNT": THREAD_DEFAULTS["GOMP_SPINCOUNT"]}
    assert env == {"KMP_BLOCKTIME": "200", "THP_MEM_ALLOC_ENABLE": "0", "GOMP_SPINCOUNT": THREAD_DEFAULTS["GOMP_SPINCOUNT"]}
    assert apply_thread_defaults({OPT_OUT_ENV: "off"}) == {}


def test_busy_cores_sees_a_competing_process():
    """A CPU-bound process beside us counts as about one busy core; the default then gives
    torch one core fewer than the machine has."""
    from clsplat.threads import busy_cores, default_torch_threads
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        import time
        time.sleep(0.3)
        busy = busy_cores(0.5)
        assert busy >= 0.7, busy
        cores = os.cpu_count()
        assert default_torch_threads(cores=cores, load=busy, active=True) <= max(1, cores - 1)
    finally:
        hog.kill()
        hog.wait()


def test_default_torch_threads_uses_idle_cores_only():
    from clsplat.threads import default_torch_threads
    assert default_torch_threads(cores=8, load=0.2, active=True) == 8
    assert default_torch_threads(cores=8, load=3.4, active=True) == 5
    assert default_torch_threads(cores=2, load=4.0, active=True) == 1
    assert default_torch_threads(cores=8, load=0.0, active=False) == 1  # spinning workers
