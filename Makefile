# objslam: the two commands are `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test install clean bench

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

## test: the whole test suite
test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/objslam bench throughput

clean:
	rm -rf $(VENV) out
