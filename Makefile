# The two set-up commands of the README: `make run` and `make test`.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: install install-test run test lint

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

install: $(BIN)/python
	$(BIN)/pip install -q -e .

install-test: $(BIN)/python
	$(BIN)/pip install -q -e '.[test]'

# The main job: a whole evolution run on this host (coordinator, trainers, evaluator over
# Zenoh on loopback), then a picture of its best bodies.
run: install
	$(BIN)/derl run --profile smoke --run-dir runs/smoke
	$(BIN)/derl unimal render runs/smoke/best --out runs/smoke/best.png

lint: install-test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/python -m pytest
