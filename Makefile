# Two commands do all the set-up on a fresh Debian 12 / Python 3.11 machine:
#   make demo   two cameras of a demo junction calibrated, one knocked, the drift watch's WARN
#   make test   run the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.semcal-installed
export OMP_NUM_THREADS ?= 2

.PHONY: demo test bench lint clean-venv

$(STAMP): requirements.txt requirements-build.txt setup.py .ci/setup-env.sh \
          $(wildcard .ci/setup.d/*.sh) $(wildcard semcal_interfaces/*/*)
	VENV=$(VENV) bash .ci/setup-env.sh
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/semcal demo

# TEST_WORKERS=2 runs the suite in two processes (idle: 373 s instead of 563 s; each test's ROS
# graph claims a domain id of its own, and --dist loadfile keeps a file's tests on one worker in
# their order, as some check what earlier tests fed a module-scoped node). Not the default: in one
# clean-clone run the two-host test's map did not complete within 150 s with both workers busy.
TEST_WORKERS ?= 0
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile test

bench: $(STAMP)
	$(VENV)/bin/semcal bench

# ruff on the whole tree (rules in ruff.toml), mypy on the engine (settings in setup.cfg); CI runs it
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy semcal_ros/engine

clean-venv:
	rm -rf $(VENV)
