# hmpf — common tasks. Everything installs into .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DATASETS ?= $(abspath ../shared/datasets)
export HMPF_DATASETS ?= $(DATASETS)
CONFIG ?= configs/default.yaml
REFERENCE ?= $(HMPF_DATASETS)/gardens_point/day_right
QUERY ?= $(HMPF_DATASETS)/gardens_point/night_right
TOLERANCE ?= 2
PIP_INSTALL := $(VENV)/bin/pip install --disable-pip-version-check -q

.PHONY: install run test bench lint format clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP_INSTALL) --upgrade pip
	$(PIP_INSTALL) -e '.[dev,cnn,index]'
	touch $@

install: $(VENV)/.installed

## run: evaluate the default hierarchy on Gardens Point day_right -> night_right
run: install
	$(VENV)/bin/hmpf-eval --config $(CONFIG) --reference $(REFERENCE) --query $(QUERY) \
		--tolerance $(TOLERANCE) --json results/eval.json

## test: the whole test suite (fails when no test is collected)
test: install
	$(PY) -m pytest -q

bench: install
	$(PY) bench/accuracy.py --out results/accuracy.json

lint: install
	$(VENV)/bin/ruff check hmpf indexer service tests bench
	$(VENV)/bin/ruff format --check hmpf indexer service tests bench

format: install
	$(VENV)/bin/ruff format hmpf indexer service tests bench
	$(VENV)/bin/ruff check --fix hmpf indexer service tests bench

clean:
	rm -rf $(VENV) results .pytest_cache .ruff_cache
