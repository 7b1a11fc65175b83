# gpis_grasp_ros — the two commands users need:
#   make demo   set up on first use, replay a bundled bag through the nodes, plan and execute a grasp
#   make test   set up on first use, lint + the whole test suite (make test-fast: the core suite alone)
SHELL := /bin/bash
.DEFAULT_GOAL := demo
ENV := source scripts/env.sh &&

# DDS stays on this machine unless you override it (e.g. on a real robot).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

BAG ?= bags/A_tape_dispenser.mcap
OUT ?= out

.PHONY: setup demo test test-fast lint bench benchmark bags clean

setup:
	@bash scripts/setup.sh

demo: setup
	@$(ENV) python -m gpis_grasp_ros.cli demo --bag $(BAG) --out $(OUT)

lint: setup
	@$(ENV) ruff check gpis_grasp_ros test scripts examples launch

test: setup
	@$(ENV) ruff check gpis_grasp_ros test scripts examples launch && python -m pytest -q -p no:cacheprovider test

# the fast core suite alone (no ROS nodes, nothing that runs on every shipped bag), a few minutes
test-fast: setup
	@$(ENV) ruff check gpis_grasp_ros test scripts examples launch && python -m pytest -q -p no:cacheprovider -m "not ros and not slow" test

bench: setup
	@$(ENV) python -m gpis_grasp_ros.bench gpis && python -m gpis_grasp_ros.bench planners

benchmark: setup
	@$(ENV) python -m gpis_grasp_ros.cli benchmark --out $(OUT)/benchmark

bags: setup
	@$(ENV) python -m gpis_grasp_ros.cli make-bags --out bags && python -m gpis_grasp_ros.cli make-bags --head --out bags

clean:
	rm -rf build install log out .venv
