# Two commands for a fresh machine with Python 3.11+; each sets up .venv on first use.
#   make demo    the whole pipeline on the built-in plant (pdtool demo)
#   make test    the test suite (what CI runs through .ci/run)
# GPU users: make demo TORCH="torch --index-url https://download.pytorch.org/whl/cu128"
# (any pip spec of your CUDA build); the default is the CPU build.

PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
DEMO_ARGS ?=
PYTEST_ARGS ?= -q

PY := $(VENV)/bin/python
PIP := $(PY) -m pip
# bpy (Blender as a module, for the real-import tests) exists for Python 3.11 only
TEST_EXTRAS = test,ray,video$(shell $(PYTHON) -c 'import sys; print(",blender" if sys.version_info[:2] == (3, 11) else "")' 2>/dev/null)

.PHONY: demo test clean-venv

demo: $(VENV)/.setup-base
	$(VENV)/bin/pdtool demo $(DEMO_ARGS)

test: $(VENV)/.setup-test
	$(PY) -m pytest $(PYTEST_ARGS)

$(VENV)/.setup-python:
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "pdtool needs Python 3.11 or newer; run: make PYTHON=python3.11 ...")'
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	@# the torch build first, so that installing the project does not pull another one
	$(PY) -c 'import torch' 2>/dev/null || $(PIP) install -q $(TORCH)
	touch $@

$(VENV)/.setup-base: $(VENV)/.setup-python pyproject.toml
	$(PIP) install -q -e .
	touch $@

$(VENV)/.setup-test: $(VENV)/.setup-python pyproject.toml
	$(PIP) install -q -e ".[$(TEST_EXTRAS)]"
	touch $@ $(VENV)/.setup-base

clean-venv:
	rm -rf $(VENV)
