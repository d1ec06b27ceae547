# The two commands a new user needs (see README.md):
#   make run    set up (no root: the venv and PyTorch), build, train locally (learner + 2 local
#               actors over shared memory) for a few minutes
#   make test   set up with the test tools (scripts/setup.sh --test: stops at once, naming the
#               package, if one is missing and cannot be installed), build, run every test
#               (this is what CI runs via .ci/run)
#   make experiments BUDGET=N   the paper's method × scene × seed grid and its report
#                               (scripts/experiments.sh documents every knob)
#   make python                 the `junction` Python package into .venv (docs/PYTHON.md)
#   make lint                   clippy over every crate and target, warnings as errors
SHELL := /bin/bash

# tch builds against the PyTorch in the project-local venv (scripts/setup.sh installs it).
export VIRTUAL_ENV := $(CURDIR)/.venv
export PATH := $(CURDIR)/.venv/bin:$(PATH)
export LIBTORCH_USE_PYTORCH := 1

CARGO ?= cargo

.PHONY: setup test-setup build python run test lint bench experiments

setup:
	@scripts/setup.sh

# Before the build, so a missing test tool stops `make test` in seconds, not after it.
test-setup:
	@scripts/setup.sh --test

build: setup
	$(CARGO) build --release --workspace --bins

run: build
	scripts/run-local.sh

# The Python package (PyO3 module, gRPC stubs, its PyPI dependencies); `make run` skips it.
python: setup
	scripts/build-python.sh

test: test-setup build python
	$(CARGO) test --release --workspace
	.venv/bin/python -m pytest -q python/tests

# Not part of `make test`: the toolchain is not pinned, and a newer clippy's new lints should
# not fail CI on code that did not change.
lint: setup
	$(CARGO) clippy --release --workspace --all-targets -- -D warnings

bench: build
	target/release/actor bench --scenario intersection

# Knobs are environment variables of scripts/experiments.sh; given on make's command line
# (make experiments BUDGET=200000 SEEDS="1 2 3") they reach it through the environment.
experiments: build
	scripts/experiments.sh
