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

# The suite runs in two processes (TEST_WORKERS=0: one). Each test's ROS graph claims a domain id
# of its own; --dist loadfile keeps a file's tests on one worker. No test waits on how fast the
# machine is: a goal that must still be running is held until the test cancels it, and streams a
# test counts are subscribed reliably, so both workers busy only make the run longer.
# SEMCAL_TEST_ORDER=reverse runs every file's tests in reverse order (tests stand alone).
TEST_WORKERS ?= 2
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
