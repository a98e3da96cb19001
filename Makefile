# RepNet: `make serve` starts the service with the bundled model, `make test` runs the whole test suite.
# Both create a virtual environment in $(VENV) (Python 3.11 with venv: Debian's python3-venv) and install
# into it. VENV= (empty) uses the current interpreter instead, as CI does after its own install.
# Extra pip arguments go in PIP_ARGS, e.g. a CPU-only torch index on machines that reach one:
#   make test PIP_ARGS="--extra-index-url https://download.pytorch.org/whl/cpu"

PYTHON3 ?= python3
VENV ?= .venv
PIP_ARGS ?=
ifeq ($(strip $(VENV)),)
PY := $(PYTHON3)
STAMP_DIR := build/.stamps
else
PY := $(VENV)/bin/python
STAMP_DIR := $(VENV)
endif
PYTEST_ARGS ?=
# Editable installs in setuptools' strict mode: a tree of links (build/__editable__*) in which service/
# is repnet and training/ repnet.train, so that tools that read files (lint-imports, mypy) see the
# package as it installs. A new module needs `make` to reinstall (touch pyproject.toml).
EDITABLE = --config-settings editable_mode=strict -e
# onnxruntime >= 1.29 sends usage telemetry on Linux unless ORT_DISABLE_TELEMETRY=1 (override: make VAR=...).
export ORT_DISABLE_TELEMETRY ?= 1
IMAGE ?= repnet:0.2.0

.PHONY: help serve test lint typecheck contracts layout check container-test image proto clean

help:
	@echo "make serve           install the service and start it (HTTP :8000, gRPC :50051)"
	@echo "make test            install everything (service, training, dev tools) and run all tests"
	@echo "make lint            ruff check;  make typecheck: mypy on repnet (strict);  make contracts: import-linter"
	@echo "make container-test  build and run the image with podman for real (root; deploy/test-container.sh)"
	@echo "make image           docker build -t $(IMAGE) .   (where a Docker engine runs)"

$(VENV)/bin/python:
	$(PYTHON3) -m venv $(VENV) || { echo "python3 -m venv failed: on Debian, apt-get install python3-venv"; exit 1; }
	$(PY) -m pip install --upgrade pip

# The service (the `server` extra) and the `repnet` command with its `cli` extra (progress bars, `repnet plot`).
$(STAMP_DIR)/.serve-installed: pyproject.toml $(if $(strip $(VENV)),$(VENV)/bin/python)
	@mkdir -p $(STAMP_DIR)
	$(PY) -m pip install $(PIP_ARGS) $(EDITABLE) '.[server,cli]'
	@touch $@

$(STAMP_DIR)/.test-installed: pyproject.toml $(if $(strip $(VENV)),$(VENV)/bin/python)
	@mkdir -p $(STAMP_DIR)
	$(PY) -m pip install $(PIP_ARGS) $(EDITABLE) '.[server,train,cli,video,dev]'
	@touch $@ $(STAMP_DIR)/.serve-installed

serve: $(STAMP_DIR)/.serve-installed
	$(PY) -m repnet serve

test: $(STAMP_DIR)/.test-installed
	$(PY) -m pytest $(PYTEST_ARGS)

lint: $(STAMP_DIR)/.test-installed
	$(PY) -m ruff check .

# mypy and import-linter read the package as it installs (service/ is repnet, training/ is
# repnet.train): build/layout/repnet is a tree of links to the two folders.
layout:
	@rm -rf build/layout && mkdir -p build/layout/repnet
	@for f in service/*; do ln -s "$(CURDIR)/$$f" build/layout/repnet/; done
	@ln -s "$(CURDIR)/training" build/layout/repnet/train

typecheck: $(STAMP_DIR)/.test-installed layout
	cd build/layout && MYPYPATH=. $(abspath $(PY)) -m mypy --config-file $(CURDIR)/pyproject.toml -p repnet

contracts: $(STAMP_DIR)/.test-installed layout
	$(dir $(PY))lint-imports --no-cache

check: lint typecheck contracts test

# The smoke checks run on this machine and need the service's own packages (grpc, httpx): the venv's.
container-test: $(STAMP_DIR)/.serve-installed
	PYTHON=$(if $(strip $(VENV)),$(abspath $(PY)),$(PY)) bash deploy/test-container.sh

image:
	docker build -t $(IMAGE) .

proto: $(STAMP_DIR)/.test-installed
	$(PY) proto/codegen.py

clean:
	rm -rf $(VENV) build .pytest_cache .mypy_cache .ruff_cache
