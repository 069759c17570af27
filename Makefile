# Two commands on a fresh machine: `make demo` and `make test`. Both bootstrap .venv from nothing.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
SEED   ?= 1

.PHONY: demo test test-slow lint bench data clean-venv

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

## demo: the workbench loop on the simulated rig (grows with each issue: log -> identify -> tune -> deploy)
demo: $(STAMP)
	$(BIN)/simulate --experiment identification --seed $(SEED) --out reports/demo/run.mcap
	$(BIN)/simulate --controller data/controller-paper.yaml --scenario all --seed $(SEED) \
		--plots reports/demo/figures

## test: the default test suite (slow tests excluded)
test: $(STAMP)
	$(BIN)/python -m pytest -q

## test-slow: only the tests marked slow
test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

lint: $(STAMP)
	$(BIN)/ruff check control identify tune tests benchmarks

## bench: print the benchmark figures
bench: $(STAMP)
	$(BIN)/python benchmarks/sim_speed.py

## data: regenerate the shipped, seeded identification-run log data/run.mcap
data: $(STAMP)
	$(BIN)/simulate --experiment identification --seed $(SEED) --out data/run.mcap

clean-venv:
	rm -rf $(VENV)
