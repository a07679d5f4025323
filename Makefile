# The two set-up commands of the README: `make demo` and `make test`.
# Both build the virtual environment .venv from setup.py on first use: `make demo` installs the eval
# extra (the demo renders its sample with scikit-image's and matplotlib's photos; the benchmark builds a
# random ONNX encoder), `make test` the test extra (the eval libraries, pytest, ruff, evo, colcon, torch).
# A plain `pip install .` is the robot's install: the node, the replay and the feature bag only.
# Each has its own stamp, so both work from one .venv in either order.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed-eval: setup.py setup.cfg package.xml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[eval]'
	touch $@

$(VENV)/.installed-test: setup.py setup.cfg package.xml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@

demo: $(VENV)/.installed-eval
	$(BIN)/nsflow-demo

test: $(VENV)/.installed-test
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

# The command docs/benchmarks.md documents: it measures for minutes and rewrites the tables under docs/results.
bench: $(VENV)/.installed-eval
	$(BIN)/nsflow-bench --tracker-seconds 10 --node-seconds 20 --background-load 0.7 --methods nsflow,klt \
		--large 1280x800 --tables docs/results

clean:
	rm -rf $(VENV) build install log *.egg-info
