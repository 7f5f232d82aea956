# Two entry points for a fresh machine: `make run` (the main job) and `make test` (the whole suite).
# Each creates .venv and installs what it needs; nothing else has to be set up by hand.
#
# Where Debian's ROS 1 packages are installed (scripts/install-ros1), .venv is made from Debian's
# Python with its system site packages, the one interpreter that imports rospy; elsewhere from
# `python3`. Installing ROS later rebuilds .venv on the next make.
#
# `.[dev]` brings every extra (ros2, secure, plot) besides the tools: the whole suite runs, the
# tests of `pip install dbml` without them included (tests/test_extras.py blocks them).
ROS_PYTHON := /usr/bin/python3
HAVE_ROS := $(shell $(ROS_PYTHON) -c 'import rospy' >/dev/null 2>&1 && echo ros1)
ifeq ($(HAVE_ROS),ros1)
PYTHON ?= $(ROS_PYTHON)
VENV_FLAGS := --system-site-packages
KIND := ros1
else
PYTHON ?= python3
VENV_FLAGS :=
KIND := plain
endif
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(KIND)

.PHONY: run run-ros1 demo-ros1 ros1 test lint typecheck pytest bench clean

$(STAMP): pyproject.toml
	rm -rf $(VENV)
	$(PYTHON) -m venv $(VENV_FLAGS) $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/dbml demo teleop

# ROS 1: Debian's packages (as root), then the scenario over a real ROS master.
ros1:
	scripts/install-ros1

run-ros1: ros1
	$(MAKE) demo-ros1

demo-ros1: $(STAMP)
	$(BIN)/dbml demo teleop --transport ros1

test: lint typecheck pytest

lint: $(STAMP)
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench

typecheck: $(STAMP)
	$(BIN)/mypy src tests bench

pytest: $(STAMP)
	$(BIN)/pytest

bench: $(STAMP)
	$(BIN)/python bench/allocate.py
	$(BIN)/python bench/reaction.py
	$(BIN)/python bench/publish_overhead.py
ifeq ($(KIND),ros1)
	$(BIN)/python bench/ros1_hz.py
endif

clean:
	rm -rf $(VENV) .mypy_cache .pytest_cache .ruff_cache .hypothesis
