# Quick start: `make demo` runs the headless demo, `make test` runs the whole suite. Both create .venv if it is
# missing and install the project into it (torch pinned to the CPU build 2.13.0 that pip finds on this machine).
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test test-gpu install clean-venv

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet "torch==2.13.0"
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/robotdemo demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

# the CUDA path, on a machine with a GPU (pip's torch here is the CPU build: install a CUDA build of torch
# into .venv first, or run `python -m pytest -m gpu` with a Python whose torch sees the GPU)
test-gpu: $(STAMP)
	$(BIN)/python -m pytest -q -m gpu

clean-venv:
	rm -rf $(VENV)
