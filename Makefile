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

# The main job (until `derl run` exists): sample a population of UNIMAL bodies, render them,
# and train a controller for the first one on flat terrain.
run: install
	$(BIN)/derl unimal sample --n 16 --seed 0 --out runs/unimals
	$(BIN)/derl unimal render runs/unimals --out runs/unimals/population.png
	$(BIN)/derl train --genome runs/unimals/unimal_0000.json --task ft --steps 200000 --out runs/train
	$(BIN)/derl rollout runs/train --episodes 2 --video runs/train/episode.gif

lint: install-test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/python -m pytest
