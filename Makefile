# Every target creates the virtual environment on first use, so that a fresh clone needs only
# `make demo` or `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export DIFFGCL_CACHE ?= $(CURDIR)/.cache

.PHONY: demo test test-slow lint format docs bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,docs]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m diffgcl.cli demo

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -m "not slow" tests

test-slow: $(STAMP)
	$(BIN)/python -m pytest -n 2 -m slow tests

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

# The API reference from the docstrings (pdoc) into site/; a warning or a broken reference fails.
docs: $(STAMP)
	$(BIN)/python docs/build_api.py site

bench: $(STAMP)
	$(BIN)/python experiments/bench_sim.py --fast

clean:
	rm -rf $(VENV) .cache runs site
