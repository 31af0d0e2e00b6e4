# Quick start: `make demo` and `make test` (each creates .venv if missing).
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast bench recordings evaluate clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip 2>/dev/null || true
	$(BIN)/python -m pip install --quiet -e '.[test,bench,viz]'
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m conductor.demo

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" tests

bench: $(STAMP)
	$(BIN)/twin bench overhead --agents 1,4,16 --ticks 2000 --out docs/results/bench_overhead.json

recordings: $(STAMP)
	$(BIN)/python recordings/make_recordings.py

evaluate: $(STAMP)
	$(BIN)/twin evaluate --json docs/results/table2.json
	$(BIN)/twin evaluate rtf --json docs/results/table1.json

clean:
	rm -rf runs .pytest_cache
