# Two entry points a fresh machine needs: `make run` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: setup run test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# Build tools first, then the project without build isolation so the C core compiles
# against the same NumPy it runs with (PYTHONWARNINGS: setuptools otherwise prints a box of
# asterisks about editable installs on every run).
setup: $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip "setuptools>=77" wheel "numpy>=2.0" "grpcio-tools>=1.60"
	PYTHONWARNINGS=ignore $(BIN)/python -m pip install -q --no-build-isolation -e '.[test]'

# The gRPC server on 127.0.0.1:50051 with the simulated devices beside it, until Ctrl-C
# (`dqpose serve --help` for TLS, tokens, ports; drop --sims for the server alone).
run: setup
	$(BIN)/dqpose serve --host 127.0.0.1 --port 50051 --sims

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python -m tests.bench.bench_core
	$(BIN)/python -m tests.bench.bench_grpc

clean:
	rm -rf $(VENV) build *.egg-info service/*.so service/rpc/_proto
