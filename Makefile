# Two commands do all the set-up on a fresh machine (see README):
#   make demo   the server with the bundled models plus a demo replay (creates .venv and installs first)
#   make test   creates .venv if missing, installs .[dev,train], runs ruff and pytest
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: test lint install demo clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch first and alone: the pinned CPU wheel satisfies `train`, so pip never resolves a CUDA build.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev,train]'
	touch $(STAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/python -m pytest

# The server with the bundled models plus a mock headset replaying a bundled recording; Ctrl-C stops.
demo: $(STAMP)
	$(BIN)/egoposevr demo

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache .hypothesis
