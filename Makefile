# ipmc-ros: the two commands of the README.
#   make demo  - set up (first run) and run the main job on the simulated rig
#   make test  - set up (first run) and run the test suite
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PKGS := ros2_ws/src/ipmc_driver ros2_ws/src/ipmc_model ros2_ws/src/ipmc_control
STAMP := $(VENV)/.installed
# One BLAS thread per process (as the ipmc command sets): the tests, benchmarks and the demo
# run fits beside node processes, and OpenBLAS threads that spin on a busy core slow a fit
# several times over.
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: demo test setup lint bench clean

setup: $(STAMP)

$(STAMP): requirements.txt $(foreach p,$(PKGS),$(p)/setup.py)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q --upgrade "pip>=23" "setuptools<80" wheel
	$(PY) -m pip install --disable-pip-version-check -q -r requirements.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps $(foreach p,$(PKGS),-e $(p)) \
		2> >(grep -v -e BuildBackendWarning -e '^ *!!' -e '^ *\*\*\*' >&2)
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/ipmc demo --out out

test: $(STAMP)
	$(PY) -m pytest -q tests $(wildcard $(addsuffix /test,$(PKGS)))

lint: $(STAMP)
	$(VENV)/bin/ruff check ros2_ws tests benchmarks scripts

bench: $(STAMP)
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) out build install log
