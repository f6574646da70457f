# hmrta: two commands for a fresh machine.
#   make demo   - run the main job on the built-in default mission
#   make test   - run the whole test suite
# Both create (or reuse) .venv/ at the repo root and install everything pinned.
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
PIP   := $(VENV)/bin/pip -q --disable-pip-version-check
PKGS  := policy ros2_ws/src/hmrta_msgs_py ros2_ws/src/hmrta_agent ros2_ws/src/hmrta_coordinator
STAMP := $(VENV)/.hmrta-installed

# DDS discovery stays on this machine unless the caller opens it up explicitly.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

.PHONY: setup demo test bench-greedy bench-ros clean-venv

setup: $(STAMP)

$(STAMP): requirements.txt policy/pyproject.toml $(wildcard ros2_ws/src/*/setup.py)
	@test -x $(PY) || python3 -m venv $(VENV)
	@# torch first, pinned: resolves to the local CPU wheel (never let a resolver pull CUDA builds)
	$(PIP) install torch==2.13.0
	$(PIP) install -r requirements.txt
	$(PIP) install --no-deps --no-build-isolation $(foreach p,$(PKGS),-e $(p))
	@touch $(STAMP)

# the main job: a live decentralised mission over ROS 2 (board, simulated robots, one agent process
# per robot, learned policy) on the built-in example; writes out/mission.json and out/mission.png
demo: setup
	$(VENV)/bin/hmrta-mission --method portfolio --out out/mission.json --check-offline

test: setup
	$(VENV)/bin/pytest -q tests

bench-greedy: setup
	$(PY) benchmarks/greedy_throughput.py

bench-ros: setup
	$(PY) benchmarks/ros_scale.py

clean-venv:
	rm -rf $(VENV)
