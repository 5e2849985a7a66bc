# Two commands do all the set-up on a fresh Debian 12 / Python 3.11 machine:
#   make demo   two cameras of a demo junction calibrated, one knocked, the drift watch's WARN
#   make test   run the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.semcal-installed
export OMP_NUM_THREADS ?= 2

.PHONY: demo test test-perturbed bench lint clean-venv

$(STAMP): requirements.txt requirements-build.txt setup.py .ci/setup-env.sh \
          $(wildcard .ci/setup.d/*.sh) $(wildcard semcal_interfaces/*/*)
	VENV=$(VENV) bash .ci/setup-env.sh
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/semcal demo

# The suite runs in three processes on two cores (TEST_WORKERS=0: one): the node tests spend part
# of their time waiting on other processes (start-up, DDS discovery), which a third worker fills
# (545 tests: 266 s against 297 s with two, idle; 571 tests now: 267 s from a clean clone).
# Each test's ROS graph claims a domain id of its own; --dist loadfile keeps a file's tests on one
# worker, and the files go out in the order test/conftest.py gives (slow ones first, then ROS
# ones): xdist's own order (most tests first) left the long ROS files to run alone at the end
# (588 tests on a slower machine: 361 s, 327 s with this order and the lighter start-up).
# No test waits on how fast the machine is: a goal that must still be running is held until the
# test cancels it, and streams a test counts are subscribed reliably, so busy workers
# only make the run longer.
# SEMCAL_TEST_ORDER=reverse runs every file's tests in reverse order (tests stand alone).
TEST_WORKERS ?= 3
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder test

# The engine and node tests again under arithmetic that differs the way another machine's does,
# the data unchanged (semcal_ros/engine/numerics.py): one render thread instead of two, the map's
# points in another order, a 1e-6 m jitter of the map, numpy without its AVX-512 paths (as on an
# AVX2-only CPU). A test that passes on one and fails on another passes by luck: no test may flip.
PERTURBED_TESTS ?= test/test_engine.py test/test_calibrate.py test/test_calibrate_and_draw.py \
	test/test_drift.py test/test_safety_drift.py test/test_quality.py test/test_search_bounds.py \
	test/test_frames.py test/test_loss.py test/test_loss_kinds.py test/test_cues.py \
	test/test_ros_calibrator.py test/test_ros_multicam.py test/test_drift_monitor.py \
	test/test_ros_e2e.py test/test_safety_nodes.py test/test_ros_monitor_window.py
PERTURBATIONS ?= NUMBA_NUM_THREADS=1 SEMCAL_PERTURB=order SEMCAL_PERTURB=jitter=1e-6 \
	NPY_DISABLE_CPU_FEATURES=X86_V4,AVX512_ICL,AVX512_SPR
test-perturbed: $(STAMP)
	@fail=0; log=$$(mktemp); for p in $(PERTURBATIONS); do \
	  echo "== $$p"; \
	  env "$$(echo $$p | tr , ' ')" $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile \
	    --no-loadscope-reorder -p no:cacheprovider $(PERTURBED_TESTS) >$$log 2>&1 || fail=1; \
	  grep -E '^(FAILED|ERROR) ' $$log || true; tail -n 1 $$log; \
	done; rm -f $$log; exit $$fail

bench: $(STAMP)
	$(VENV)/bin/semcal bench

# ruff on the whole tree (rules in ruff.toml), mypy on the engine (settings in setup.cfg); CI runs it
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy semcal_ros/engine

clean-venv:
	rm -rf $(VENV)
