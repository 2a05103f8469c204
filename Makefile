# The two commands of the README. Both set up what they need (idempotent; fast once installed).
SHELL := /bin/bash
VENV := .venv
export LIBTORCH_USE_PYTORCH := 1
export PYO3_PYTHON := $(CURDIR)/$(VENV)/bin/python

.PHONY: run test setup
setup:
	scripts/setup.sh

# Set up, then run the embedded default: PointMaze from freshly generated demos.
run: setup
	scripts/run-default.sh

# Set up, then run every test (Rust and Python).
test: setup
	scripts/test.sh
