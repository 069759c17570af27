# Two commands on a fresh machine: `make demo` and `make test`. Both bootstrap .venv from nothing.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
SEED   ?= 1
TRIALS ?= 200
# pytest-xdist workers for make test / test-slow (auto: one per core; 0 runs in one process).
# A test file stays on one worker (--dist loadfile), so its module fixtures are built once.
TEST_WORKERS ?= auto
PYTEST := $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

.PHONY: demo test test-slow lint bench data clean-venv

# the install also compiles the control law's C (control/law/c) into the library numba calls
$(STAMP): pyproject.toml $(wildcard control/law/c/*.c control/law/c/*.h)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

## demo: the whole loop on the simulated rig: log -> identify -> tune -> deploy -> reports/summary.md
## (the identification run logs every 0.5 ms, so identify estimates the moving mass too). The rig
## is the paper's with real-rig effects (PLANT: data/plant-paper-rig.yaml, which reproduces
## Table 1 with the paper's gains); PLANT= (empty) runs the ideal rig of the paper's model.
PLANT  ?= data/plant-paper-rig.yaml
RIG    := sim$(if $(PLANT),:$(PLANT))
demo: $(STAMP)
	$(BIN)/record --experiment identification --rig $(RIG) --seed $(SEED) \
		--out reports/demo/run.mcap
	$(BIN)/identify reports/demo/run.mcap --out reports/identify
	$(BIN)/tune --model reports/identify/model.yaml --trials $(TRIALS) --seed $(SEED) \
		--out reports/tune
	mkdir -p reports/deploy
	$(BIN)/deploy data/controller-paper.yaml --rig $(RIG) --scenario all --seed $(SEED) --json \
		--log reports/deploy/paper.mcap --plots reports/deploy/figures-paper \
		> reports/deploy/paper.json
	$(BIN)/deploy reports/tune/controller.yaml --rig $(RIG) --scenario all --seed $(SEED) --json \
		--log reports/deploy/tuned.mcap --plots reports/deploy/figures-tuned \
		> reports/deploy/tuned.json
	$(BIN)/python -m pneutune.control.summary --paper reports/deploy/paper.json \
		--tuned reports/deploy/tuned.json --figures reports/deploy/figures-tuned \
		--out reports/summary.md
	@cat reports/summary.md

## test: the default test suite (slow tests excluded)
test: $(STAMP)
	$(PYTEST)

## test-slow: only the tests marked slow
test-slow: $(STAMP)
	$(PYTEST) -m slow

## lint: ruff, and the import layers of pneutune.control (import-linter, pyproject.toml)
lint: $(STAMP)
	$(BIN)/ruff check control identify tune tests benchmarks
	$(BIN)/lint-imports

## bench: print the benchmark figures
bench: $(STAMP)
	$(BIN)/python benchmarks/sim_speed.py
	$(BIN)/python benchmarks/closed_loop.py
	$(BIN)/python benchmarks/identify_speed.py
	$(BIN)/python benchmarks/runtime_latency.py
	$(BIN)/python benchmarks/tune_speed.py

## data: regenerate the shipped, seeded identification-run log data/run.mcap
data: $(STAMP)
	$(BIN)/record --experiment identification --seed $(SEED) --compression-level 19 \
		--out data/run.mcap

clean-venv:
	rm -rf $(VENV)
