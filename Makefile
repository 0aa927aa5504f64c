# The two contract commands are `make demo` and `make test` (README). Both set the project up first.
SHELL := /bin/bash
MM := ./mm

.PHONY: setup demo test bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(MM) run mm_bringup demo --output results/demo_bag

test: setup
	$(MM) python -m pytest

bench: setup
	$(MM) python -m mm_bringup.bench --output results

clean:
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log ros2_ws/build.log results/demo_bag results/tmp
