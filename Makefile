# mocapd — the two commands of the README's Quick start are `make demo` and `make test`.
# Both run the project's own set-up first (setup/setup.sh): it installs what is missing and is
# a no-op when everything is already in place.
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test lint typecheck unit bench clean

setup:
	@bash setup/setup.sh

demo: setup
	$(BIN)/mocapd demo

test: setup lint typecheck unit

lint:
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck:
	$(BIN)/mypy

unit:
	$(BIN)/pytest -q

bench: setup
	$(BIN)/mocapd bench solver

clean:
	rm -rf $(VENV) .mypy_cache .pytest_cache .ruff_cache build *.egg-info
