# The two README commands:  `make demo`  and  `make test`.
# Each sets everything up on a fresh Debian 12 / Ubuntu 24.04 machine (system packages,
# .venv, CPU torch, the project in editable mode with its C++ extension) and then runs.
# A second run skips the set-up it already did (stamp file .venv/.rayfronts-setup).

PY      ?= python3
VENV    ?= .venv
TORCH   ?= torch==2.13.0
EXTRAS  ?= all,test
STAMP   := $(VENV)/.rayfronts-setup
OUT     ?= out/demo
PYTEST_ARGS ?=

.PHONY: setup demo test bench clean-build

setup: $(STAMP)

$(STAMP): pyproject.toml CMakeLists.txt $(wildcard mapper/csrc/*) deploy/setup_dev.sh
	PY=$(PY) VENV=$(VENV) TORCH='$(TORCH)' EXTRAS='$(EXTRAS)' bash deploy/setup_dev.sh
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/rayfronts demo --out $(OUT)

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -p no:cacheprovider $(PYTEST_ARGS)

bench: $(STAMP)
	$(VENV)/bin/rayfronts bench world --json out/bench_world.json

clean-build:
	rm -rf build $(STAMP)
