# The two set-up commands of the README: `make demo` and `make test`.
# Both build the virtual environment .venv from setup.py on first use: `make demo` installs only what
# the package needs at run time, `make test` adds the test extra (pytest, ruff, evo, colcon, torch).
# Each has its own stamp, so both work from one .venv in either order.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed-run: setup.py setup.cfg package.xml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: setup.py setup.cfg package.xml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@

demo: $(VENV)/.installed-run
	$(BIN)/nsflow-demo

test: $(VENV)/.installed-test
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

bench: $(VENV)/.installed-run
	$(BIN)/nsflow-bench

clean:
	rm -rf $(VENV) build install log *.egg-info
