# LSU workspace. `make demo` and `make test` set everything up themselves (see README.md).
SHELL := /bin/bash
.DEFAULT_GOAL := help
ROOT := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))
VENV := $(ROOT)/.venv
LSU := $(VENV)/bin/lsu
PYTEST_ARGS ?=

# DDS never leaves this machine; every run gets its own domain unless the caller chose one
# (the test fixtures and `lsu demo` additionally claim a domain no other run on this machine holds).
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= $(shell echo $$(( $$$$ % 100 + 1 )))
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: help setup demo lint test test-faults bench lock clean distclean

help:
	@echo "make setup   - create .venv, install pinned ROS 2 Jazzy wheels, build lsu_interfaces (idempotent)"
	@echo "make demo    - set up if needed, run the LSU graph on the emulated unit and show what it does"
	@echo "make lint    - ruff check, then mypy over every package under src/ (settings: pyproject.toml)"
	@echo "make test    - set up if needed, lint, run the whole test suite (2 workers, then the serial tests)"
	@echo "make test-faults - only the fault-injection tests; summary in test-results/faults.json"
	@echo "make bench   - run the benchmarks, JSON in bench/results/ and a table in bench/results/SUMMARY.md"
	@echo "make lock    - resolve requirements.in into requirements.lock (keeps existing pins; tools/lock.py --upgrade moves them)"
	@echo "make clean   - remove build/ log/ (keeps .venv); make distclean also removes .venv"

setup:
	@bash $(ROOT)/tools/bootstrap.sh

demo: setup
	$(LSU) demo

# ruff over every Python file of the workspace, mypy over the packages (the file patterns are in
# pyproject.toml, so new packages are included); mypy's cache lives in .venv
lint: setup
	cd $(ROOT) && $(VENV)/bin/ruff check && $(VENV)/bin/mypy

# The suite in two parts, each with its own summary; it fails if either part failed:
#  1. all but the timing-sensitive tests on PYTEST_WORKERS pytest-xdist workers (each worker claims its
#     own ROS domain; a test module stays on one worker, so its module fixtures are built once; modules
#     with slow tests are handed out first, see lsu_testing.plugin),
#  2. the tests marked serial and the fault-injection tests, alone in one process.
# Exit status 5 (no test selected) of one part is no failure: PYTEST_ARGS may name tests of one part only.
# Three workers on two cores: the graph tests wait on real time (processes starting, DDS discovery, the
# emulated motor), which left a third of two workers' CPU idle; a test that fails under the extra load is a
# defect of the test or the code (a fresh clone here: the parallel part 576 s with two workers, 436 s with three)
PYTEST_WORKERS ?= 3
# the slowest tests are named in the log of every run
DURATIONS ?= --durations=30 --durations-min=5
test: lint
	cd $(ROOT) && par=0 && ser=0; \
	$(VENV)/bin/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder $(DURATIONS) -m "not serial and not fault" $(PYTEST_ARGS) \
		|| par=$$?; \
	$(VENV)/bin/python -m pytest $(DURATIONS) -m "serial or fault" $(PYTEST_ARGS) || ser=$$?; \
	if [ $$par = 5 ] && [ $$ser = 5 ]; then exit 5; fi; \
	for rc in $$par $$ser; do [ $$rc = 0 ] || [ $$rc = 5 ] || exit $$rc; done

# the fault-injection suite alone (make test runs it too); summary in test-results/faults.json
test-faults: setup
	cd $(ROOT) && $(VENV)/bin/python -m pytest -m fault $(PYTEST_ARGS)

bench: setup
	@ls $(ROOT)/bench/bench_*.py >/dev/null 2>&1 || { echo "no benchmarks yet"; exit 0; }; \
	for b in $(ROOT)/bench/bench_*.py; do $(VENV)/bin/python $$b || exit 1; done; \
	$(VENV)/bin/python $(ROOT)/bench/summary.py

bench-%: setup
	$(VENV)/bin/python $(ROOT)/bench/bench_$*.py

lock:
	$(or $(wildcard $(VENV)/bin/python),python3) $(ROOT)/tools/lock.py

clean:
	rm -rf $(ROOT)/build $(ROOT)/log

distclean: clean
	rm -rf $(VENV)
