# Every target creates the virtual environment on first use, so that a fresh clone needs only
# `make demo` or `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export DIFFGCL_CACHE ?= $(CURDIR)/.cache

.PHONY: demo test test-slow lint format docs bench clean peers

# uv resolves and downloads in parallel (about 10 s here against 50 s for pip); pip takes over
# where uv cannot be installed or cannot reach the index.
$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	( $(BIN)/python -m pip install --quiet uv && \
	  $(BIN)/uv pip install --quiet --python $(BIN)/python -e '.[dev,docs]' ) || \
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

# The peer stack (imitation, stable-baselines3, torch CPU) beside diffgcl in a virtual environment
# of its own, experiments/peers/.venv (docs/peers.md); then run experiments/peers/vs_imitation.py.
# torch's CPU build comes first, from PyTorch's CPU index (TORCH_INDEX= leaves it to PyPI and
# local wheels), so that only torch and its few dependencies are looked up there.
PEERS := experiments/peers/.venv
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
$(PEERS)/.installed: experiments/peers/requirements.txt experiments/peers/no-deps.txt pyproject.toml
	$(PY) -m venv $(PEERS)
	$(PEERS)/bin/python -m pip install --quiet --upgrade pip
	$(PEERS)/bin/python -m pip install --quiet torch==2.13.0 \
		$(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX))
	$(PEERS)/bin/python -m pip install --quiet -e '.[dev,gym]' -r experiments/peers/requirements.txt
	$(PEERS)/bin/python -m pip install --quiet --no-deps -r experiments/peers/no-deps.txt
	touch $(PEERS)/.installed

peers: $(PEERS)/.installed

clean:
	rm -rf $(VENV) .cache runs site
