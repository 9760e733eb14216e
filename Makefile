# Two entry points a fresh machine needs: `make run` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
EXTRAS := devices,planning,plot,record,view,yaml,test,lint
# Extra arguments: `make run ARGS="--port 50052"` (dqpose serve's options; the last of a repeated
# option wins), `make test ARGS="-k blend"` (pytest's).
ARGS   ?=

# The install is redone only when one of its inputs changed: Python sources are an editable
# install, but the C core, the generated stubs and the dependency lists are built from these.
# A missing C core or stub folder (deleted by hand) forces it too.
STAMP  := $(VENV)/.installed
INPUTS := Makefile pyproject.toml setup.py $(wildcard service/csrc/*.c service/csrc/*.h) \
          $(shell find proto -name '*.proto')
MISSING := $(if $(wildcard service/_dqcore*.so),,FORCE) \
           $(if $(wildcard service/rpc/_proto/dqpose/v1/*_pb2.py),,FORCE)

.PHONY: setup run cluster test test-fast lint bench clean FORCE

$(BIN)/python:
	@echo "make: creating the virtual environment $(VENV) (a few seconds)"
	$(PYTHON) -m venv $(VENV)

# Build tools first, then the project without build isolation so the C core compiles
# against the same NumPy it runs with (PYTHONWARNINGS: setuptools otherwise prints a box of
# asterisks about editable installs on every run).
$(STAMP): $(INPUTS) $(MISSING) | $(BIN)/python
	@echo "make: installing the build tools into $(VENV): pip, setuptools, wheel, numpy, grpcio-tools (~15 s the first time)"
	$(BIN)/python -m pip install -q --upgrade pip "setuptools>=77" wheel "numpy>=2.0" "grpcio-tools==1.85.1"
	@echo "make: installing dqpose[$(EXTRAS)] and its dependencies, building the C core, generating the gRPC stubs (~1-2 min and ~300 MB of downloads the first time, ~5 s after a change)"
	PYTHONWARNINGS=ignore $(BIN)/python -m pip install -q --no-build-isolation -e '.[$(EXTRAS)]'
	@touch $@

FORCE:

setup: $(STAMP)

# The gRPC server on 127.0.0.1:50051 with the simulated devices beside it, until Ctrl-C
# (`dqpose serve --help` for TLS, tokens, ports; ARGS after the defaults, so they override them).
run: setup
	$(BIN)/dqpose serve --host 127.0.0.1 --port 50051 --sims $(ARGS)

# Three replicas of the server and HAProxy in front of them on 127.0.0.1:50050, the proxy running
# docker/haproxy.cfg with its server lines rewritten to the replicas, until Ctrl-C (`dqpose cluster
# --help`; needs haproxy: apt-get install -y haproxy): make cluster ARGS="--replicas 5".
cluster: setup
	$(BIN)/dqpose cluster --config docker/haproxy.cfg $(ARGS)

# The suite without the fresh-venv installs (pytest's addopts: -m 'not install'); CI runs those
# after it: make test ARGS="-m install".
test: setup
	$(BIN)/python -m pytest -q $(ARGS)

# ruff over the tree; mypy over the package, read through a tree of links named as it imports
# (dqpose/ = service/, dqpose/drivers/ = drivers/), since the folders keep the layout's names
lint: setup
	$(BIN)/ruff check .
	rm -rf build/mypy && mkdir -p build/mypy/dqpose
	ln -s $(CURDIR)/service/* build/mypy/dqpose/ && ln -s $(CURDIR)/drivers build/mypy/dqpose/drivers
	cd build/mypy && $(CURDIR)/$(BIN)/mypy --config-file $(CURDIR)/pyproject.toml
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/test_lengths.py tests/test_layout.py

# The inner loop: the suite without the slow modules (tests/conftest.py), the heaviest requests
# and the installs; a few minutes. `make test` still runs everything.
test-fast: setup
	$(BIN)/python -m pytest -q -m "not slow and not heavy and not install" $(ARGS)

bench: setup
	$(BIN)/python -m tests.bench.bench_core
	$(BIN)/python -m tests.bench.bench_grpc
	$(BIN)/python -m tests.bench.bench_fusion_core
	$(BIN)/python -m tests.bench.bench_fusion
	$(BIN)/python -m tests.bench.bench_trajectory
	$(BIN)/python -m tests.bench.bench_smoothing
	$(BIN)/python -m tests.bench.bench_executor
	$(BIN)/python -m tests.bench.bench_handeye
	$(BIN)/python -m tests.bench.bench_handeye_kinhec

clean:
	rm -rf $(VENV) build *.egg-info service/*.so service/rpc/_proto
