# The two commands of the README: `make demo` and `make test`.  Both set
# everything up first (tools/bootstrap.sh: .venv, pinned ROS 2 wheels, colcon build).
SHELL := /bin/bash
IN_ENV := source tools/env.sh &&

.PHONY: demo test bootstrap lint bench clean

bootstrap:
	@bash tools/bootstrap.sh

demo: bootstrap
	@$(IN_ENV) install/sonar_ring/lib/sonar_ring/demo

test: bootstrap
	@$(IN_ENV) pytest

lint: bootstrap
	@$(IN_ENV) ruff check sonar_ring test bench launch setup.py

bench: bootstrap
	@$(IN_ENV) sonar-ring bench

clean:
	rm -rf build install log demo_output .venv
