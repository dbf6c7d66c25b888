# `make run` and `make test` set up everything they need in .venv by themselves.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-dev
CONFIG ?= configs/mock_arm.toml
ARGS ?= --duration 5

.PHONY: run test check bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install -q -e '.[dev,sim]'
	touch $@

run: $(STAMP)
	$(PY) -m aiohal $(CONFIG) $(ARGS)

test: $(STAMP)
	$(PY) -m pytest

check: $(STAMP)
	$(PY) -m aiohal check $(CONFIG)

clean:
	rm -rf $(VENV) build *.egg-info
