# Quick start: `make demo` and `make test` (each creates .venv if missing).
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast lint bench bench-scale limit recordings evaluate heldout clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip 2>/dev/null || true
	$(BIN)/python -m pip install --quiet -e '.[test,bench,viz]'
	@# the project's bytecode, once: where PYTHONDONTWRITEBYTECODE is set (this machine, CI) every agent process
	@# would otherwise compile every module it imports, each time it starts
	$(BIN)/python -m compileall -q agents protocol conductor bench recordings > /dev/null
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m conductor.cli.demo

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

# quality gates (CI runs them beside the tests): ruff, mypy at the settings in pyproject.toml, and mypy
# --strict on the contract (protocol/) and the model author's API (agents/)
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m mypy protocol agents conductor recordings bench
	$(BIN)/python -m mypy --strict --follow-imports=silent protocol agents/__init__.py agents/model.py \
		agents/runtime.py agents/testing.py agents/__main__.py agents/registry.py

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" tests

bench: $(STAMP)
	$(BIN)/twin bench overhead --agents 1,4,16 --ticks 2000 --out docs/results/bench_overhead.json
	$(BIN)/python -m bench.model_rates docs/results/bench_models.json
	$(BIN)/python -m bench.fluid_rates --json docs/results/bench_fluid.json
	$(BIN)/python -m bench.viewer_cost --scene scenes/ball_drop.yaml --recording recordings/ball_drop_00.mcap --rounds 8 --json docs/results/bench_viewer.json

# the speed limit: the same models in one process without the framework, side by side with twin run
limit: $(STAMP)
	$(BIN)/python -m bench.limit --rounds 9 --json docs/results/limit.json

bench-scale: $(STAMP)
	$(BIN)/twin bench scale --agents 4,16,64 --hosts 1,4 --ticks 300

recordings: $(STAMP)
	$(BIN)/python recordings/make_recordings.py

evaluate: $(STAMP)
	$(BIN)/twin evaluate --configs ensemble,baseline1,baseline2,baseline3,mujoco_grasp,mujoco --json docs/results/table2.json --table docs/results/table2.md
	$(BIN)/twin evaluate rtf --repeat 7 --json docs/results/table1.json --table docs/results/table1.md

# the team's held-out recordings (seeds 7001-7032, never used elsewhere), generated afresh, then evaluated
heldout: $(STAMP)
	$(BIN)/python -m bench.heldout --out runs/heldout
	$(BIN)/twin evaluate --recordings runs/heldout --json docs/results/heldout.json --table docs/results/heldout.md

clean:
	rm -rf runs .pytest_cache
