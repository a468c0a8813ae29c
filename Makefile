# mocapd — the two commands of the README's Quick start are `make demo` and `make test`.
# Both run the project's own set-up first (setup/setup.sh): it installs what is missing and is
# a no-op when everything is already in place. `make demo` runs the demo profile (the daemon, Aravis, the demo
# videos and the detector models); `make test` the test profile (all of that and the test stack: dev tools,
# PyTorch, Pose2Sim, Chromium, Node.js, Mono, Blender's bpy). `make setup` is the test profile.
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-demo demo test lint typecheck typecheck-and-warm unit bench clean

setup:
	@bash setup/setup.sh test

setup-demo:
	@bash setup/setup.sh demo

demo: setup-demo
	$(BIN)/mocapd demo

test: setup lint typecheck-and-warm unit

lint:
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck:
	$(BIN)/mypy

# mypy uses one core; on the other, every numba kernel compiles into its on-disk cache (tools/warm_kernels.py:
# ~130 s of CPU on a clean checkout, which the tests paid one kernel at a time). A failure of either fails it.
# First the checkout's bytecode (__pycache__, 1.4 s of CPU): where PYTHONDONTWRITEBYTECODE is set (as in a Python
# container's environment) no interpreter writes it, and each of the suite's hundreds of `mocapd` and helper
# processes compiled every module it imported again (0.7 s of CPU of a `mocapd check-config`'s 2.7 s).
typecheck-and-warm:
	@{ $(BIN)/python -m compileall -q -x node_modules mocapd tools tests && $(BIN)/python -m tools.warm_kernels; } & warm=$$!; \
	$(BIN)/mypy; rc=$$?; \
	wait $$warm || rc=1; \
	exit $$rc

# --durations: every run (CI's included) ends with its 40 slowest tests, the numbers to act on when the suite slows.
unit:
	$(BIN)/pytest -q --durations=40

bench: setup-demo
	$(BIN)/mocapd bench solver

clean:
	rm -rf $(VENV) .mypy_cache .pytest_cache .ruff_cache build *.egg-info
