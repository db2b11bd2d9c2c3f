# objslam: the two commands are `make run` and `make test` (`make lint`: ruff and mypy, as the pre-commit hooks).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint install clean bench

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install --quiet -e ".[test,train]"
	touch $(STAMP)

install: $(STAMP)

## run: the whole pipeline on the built-in synthetic scene over an embedded zenoh session
run: $(STAMP)
	$(BIN)/objslam run "synthetic:room?seed=0&frames=300" --out out/run

## test: lint, format and types first (CI fails on a violation), then the whole test suite
test: lint
	$(BIN)/python -m pytest -q

## lint: ruff (lint, then the format check) and mypy over the packages in pyproject.toml
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/objslam bench throughput

clean:
	rm -rf $(VENV) out
