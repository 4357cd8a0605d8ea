"""clsplat.threads: the OpenMP wait policy set once at import, before torch loads."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from clsplat.threads import OPT_OUT_ENV, THREAD_DEFAULTS, apply_thread_defaults

# The documented way: import clsplat before torch. The child reports its own environment,
# whether clsplat judged the defaults active, and what a grandchild process inherits.
_CHILD = """
import json, os, subprocess, sys
import clsplat, torch
from clsplat.threads import thread_defaults_active
grand = subprocess.run([sys.executable, "-c", "import os, json; print(json.dumps({k: os.environ.get(k) for k in %r}))"],
                       capture_output=True, text=True, check=True).stdout
print(json.dumps({"env": {k: os.environ.get(k) for k in %r}, "active": thread_defaults_active(),
                  "grandchild": json.loads(grand)}))
""" % (sorted(THREAD_DEFAULTS), sorted(THREAD_DEFAULTS))


def _child(**env) -> dict:
    base = {k: v for k, v in os.environ.items() if k not in THREAD_DEFAULTS and k != OPT_OUT_ENV}
    r = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, timeout=120,
                       env={**base, **env})
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_child_importing_clsplat_first_gets_the_defaults():
    got = _child()
    assert got["env"] == THREAD_DEFAULTS
    assert got["grandchild"] == THREAD_DEFAULTS  # inherited by processes it starts
    assert got["active"] is True


def test_opt_out_leaves_the_environment_alone():
    got = _child(**{OPT_OUT_ENV: "0"})
    assert got["env"] == {k: None for k in THREAD_DEFAULTS}
    assert got["active"] is False


def test_user_values_win():
    got = _child(OMP_WAIT_POLICY="ACTIVE")
    assert got["env"]["OMP_WAIT_POLICY"] == "ACTIVE"
    assert got["env"]["KMP_BLOCKTIME"] == THREAD_DEFAULTS["KMP_BLOCKTIME"]
    assert got["active"] is False  # spinning workers: the single-thread default stays


def test_apply_sets_only_what_is_unset():
    env = {"KMP_BLOCKTIME": "200"}
    assert apply_thread_defaults(env) == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert env == {"KMP_BLOCKTIME": "200", "OMP_WAIT_POLICY": "PASSIVE"}
    assert apply_thread_defaults({OPT_OUT_ENV: "off"}) == {}


def test_default_torch_threads_uses_idle_cores_only():
    from clsplat.threads import default_torch_threads
    assert default_torch_threads(cores=8, load=0.2, active=True) == 8
    assert default_torch_threads(cores=8, load=3.4, active=True) == 5
    assert default_torch_threads(cores=2, load=4.0, active=True) == 1
    assert default_torch_threads(cores=8, load=0.0, active=False) == 1  # spinning workers
