# Two entry points a fresh machine needs: `make run` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: setup run test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# Build tools first, then the project without build isolation so the C core compiles
# against the same NumPy it runs with.
setup: $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip "setuptools>=77" wheel "numpy>=2.0" "grpcio-tools>=1.60"
	$(BIN)/python -m pip install -q --no-build-isolation -e '.[test]'

run: setup
	$(BIN)/dqpose demo

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python -m tests.bench.bench_core

clean:
	rm -rf $(VENV) build *.egg-info service/*.so
