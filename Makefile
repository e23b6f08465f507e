# The two set-up commands of the README: `make run` and `make test`.
# The first Python >= 3.11 on PATH (python3.11 first: the local CPU torch wheel is built for it).
PYTHON ?= $(shell for p in python3.11 python3.12 python3.13 python3; do \
	command -v $$p >/dev/null 2>&1 && $$p -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
	2>/dev/null && { echo $$p; break; }; done)
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: install install-test run test ruff lint typecheck mypy clips

$(BIN)/python:
	@test -n "$(PYTHON)" || { echo "derl needs Python >= 3.11 (none found on PATH; set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

install: $(BIN)/python
	$(BIN)/pip install -q -e .

install-test: $(BIN)/python
	$(BIN)/pip install -q -e '.[test]'

# The main job: a whole evolution run on this host (coordinator, trainers, evaluator over
# Zenoh on loopback), then a picture of its best bodies and a short clip of the best one
# (a pipeline check: a smoke body trained 8,192 steps does not walk).
run: install
	$(BIN)/derl run --profile smoke --run-dir runs/smoke
	$(BIN)/derl unimal render runs/smoke/best --out runs/smoke/best.png
	$(BIN)/derl rollout runs/smoke/best/01-* --episodes 1 --episode-steps 150 \
		--video runs/smoke/best.gif

# The README's clips, filmed from the agents shipped in agents/ (each a `derl train` folder:
# genome.json, checkpoint.pt, result.json), 320x240: FT 250 control steps (5 s) at real
# speed (every 2nd frame), VT 500 (10 s: past its first obstacles) and MVT a whole episode (20 s:
# its box is 15-24 m ahead) at twice and four times it.
clip = $(BIN)/derl rollout agents/$(1) --episodes 1 --episode-steps $(2) --video-size 320x240 \
	--video-every $(3) --video docs/clips/$(1).gif

clips: install
	$(call clip,ft,250,2)
	$(call clip,vt,500,4)
	$(call clip,mvt,1000,8)

# mypy on the package as installed: `derl`, with messages/ and nodes/ as `derl.messages` and
# `derl.nodes` (pyproject's package-dir, which the editable install maps by an import hook mypy
# cannot follow), read through setuptools' strict editable tree: the package's files linked as
# installed, in build/__editable__.derl-*, made afresh each time by the build backend's PEP 660
# hook (as `pip install -e . --config-settings editable_mode=strict` does, without installing);
# its messages name the repository's files. Options in pyproject's [tool.mypy]; tests/ and bench/
# are not checked. Its cache stays in build/typecheck/.mypy_cache: a first check takes about 30 s
# of CPU, a later one a few seconds.
TYPECHECK := build/typecheck
define typecheck
rm -rf build/__editable__.derl-* && mkdir -p $(TYPECHECK)
$(BIN)/python -c "import setuptools.build_meta as backend; \
	backend.build_editable('$(TYPECHECK)', {'editable_mode': 'strict'})" \
	>$(TYPECHECK)/build.txt 2>&1 || { cat $(TYPECHECK)/build.txt; exit 1; }
cd build/__editable__.derl-* && { $(abspath $(BIN))/mypy --config-file $(CURDIR)/pyproject.toml \
	--cache-dir $(CURDIR)/$(TYPECHECK)/.mypy_cache -p derl >$(CURDIR)/$(TYPECHECK)/mypy.txt; \
	status=$$?; sed -e 's#^derl/messages/#messages/#' -e 's#^derl/nodes/#nodes/#' \
	$(CURDIR)/$(TYPECHECK)/mypy.txt; exit $$status; }
endef

ruff: install-test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

lint: ruff typecheck

typecheck: install-test mypy

# Four test processes (pytest-xdist) on 2 cores: many tests wait on nodes (leases, restarts,
# Zenoh) while others compute, so four keep both cores busier than two (measured on one commit:
# 1,026 s with -n 2, 797 s with -n 4, the cores 89% busy; `pytest` alone runs it serially).
# `loadgroup` keeps a module's `xdist_group` on one process (its module fixture made once);
# the 20 slowest tests are listed at the end. mypy (single-threaded, a minute from a fresh
# clone) runs beside the tests, its report printed after theirs; either failing fails `make test`.
test: ruff
	@mkdir -p $(TYPECHECK)
	@$(MAKE) --no-print-directory mypy >$(TYPECHECK)/report.txt 2>&1 & checking=$$!; \
	$(BIN)/python -m pytest -n 4 --dist loadgroup --durations=20; tested=$$?; \
	wait $$checking; checked=$$?; cat $(TYPECHECK)/report.txt; \
	exit $$(( tested ? tested : checked ))

# mypy alone, derl installed (`make test` runs it so)
mypy:
	$(typecheck)
