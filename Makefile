# Two entry points (see README.md): `make demo` runs the main job, `make test` runs the tests
# (all of them, the 15 slowest listed; `make check` is the quick tier without the `slow` marker).
# Both create .venv on first use and install the pinned dependencies from setup.cfg and
# constraints.txt; the stamp makes later runs skip the install until those files change.
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.clsplat-installed
OUT    ?= out

.PHONY: demo test check bench info wheel-smoke

$(STAMP): setup.cfg pyproject.toml constraints.txt
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/clsplat demo --out $(OUT)

# on every core (pytest-xdist): one group per test module, the modules that read one session-trained
# run in one group (tests/conftest.py), the groups with the most slow tests first
test: $(STAMP)
	POCL_MAX_WORK_GROUP_SIZE=256 $(VENV)/bin/pytest -q -n auto --dist loadgroup --durations=15 tests

# the edit-test loop: everything but what trains, spawns interpreters, simulates or drives a browser,
# on every core (pytest-xdist; the quick tier spawns nothing, tests/test_tiers.py sees to it)
check: $(STAMP)
	POCL_MAX_WORK_GROUP_SIZE=256 $(VENV)/bin/pytest -q -n auto -m "not slow" tests

bench: $(STAMP)
	$(VENV)/bin/clsplat bench all --out bench/out

info: $(STAMP)
	$(VENV)/bin/clsplat info

# the built wheel in a fresh venv over an older numpy/pandas: clsplat info and a tiny render
wheel-smoke: $(STAMP)
	PYTHON=$(PY) .ci/wheel_smoke $(SMOKE_DIR)
