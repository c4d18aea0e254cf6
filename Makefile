# The verbs people type. Every target that runs code depends on .venv, so each
# one works on a fresh machine by itself.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup run test test-fast lint bench tables tables-check clean

setup: $(STAMP)

# Re-install only when the dependency list changes (idempotent, fast when done).
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

run: $(STAMP)
	$(PY) -m hil run --route full_road_section --mode auto --seed 1 --pace lockstep --out out/run

# the whole suite: the layer contracts, then every test (HIL, golden traces and slow ones too)
test: lint
	$(PY) -m pytest -q -n 2 --dist loadgroup

# the unit tier: no HIL, no golden traces, no long simulation (a minute or so on a warm machine)
test-fast: lint
	$(PY) -m pytest -q -n 2 -m "not hil and not slow and not golden"

# the import layers firmware <- calib <- hil <- tools (import-linter contracts in pyproject.toml)
lint: $(STAMP)
	$(VENV)/bin/lint-imports --no-cache

# benchmarks: out/bench.json and a table (run on an idle machine)
bench: $(STAMP)
	$(PY) -m tools.bench --out out/bench.json

# C-portable coefficient tables (c/generated/ecu_tables.h/.c); -check fails when stale
tables: $(STAMP)
	$(PY) -m tools.tables --out c/generated

tables-check: $(STAMP)
	$(PY) -m tools.tables --out c/generated --check

clean:
	rm -rf $(VENV) out .pytest_cache
