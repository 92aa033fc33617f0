# The two README commands:  `make demo`  and  `make test`.
# Each sets everything up on a fresh Debian 12 / Ubuntu 24.04 machine (system packages,
# .venv, CPU torch, the project in editable mode with its C++ extension) and then runs.
# A second run skips the set-up it already did (stamp files .venv/.rayfronts-setup-*).
# `make demo` sets up the runtime extras only; `make test` adds the test extra (pytest and
# Debian's chromium for the browser test).

comma   := ,
PY      ?= python3
VENV    ?= .venv
TORCH   ?= torch==2.13.0
EXTRAS  ?= all,test
DEMO_EXTRAS ?= all
OUT     ?= out/demo
PYTEST_ARGS ?=
# test files spread over this many pytest-xdist workers (a file stays on one worker: its
# module fixtures are shared); 0 runs them in this process, one after another
TEST_WORKERS ?= 2
SETUP_DEPS := pyproject.toml CMakeLists.txt $(wildcard semantic_map/csrc/*) deploy/setup_dev.sh
STAMP      := $(VENV)/.rayfronts-setup-$(subst $(comma),-,$(EXTRAS))
DEMO_STAMP := $(VENV)/.rayfronts-setup-$(subst $(comma),-,$(DEMO_EXTRAS))

.PHONY: setup demo test lint typecheck bench clean-build

setup: $(STAMP)

$(VENV)/.rayfronts-setup-%: $(SETUP_DEPS)
	PY=$(PY) VENV=$(VENV) TORCH='$(TORCH)' EXTRAS='$(subst -,$(comma),$*)' bash deploy/setup_dev.sh
	touch $@

demo: $(DEMO_STAMP)
	$(VENV)/bin/rayfronts demo --out $(OUT)

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -rs -p no:cacheprovider --durations=30 -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

# ruff with the rule set in pyproject.toml ([tool.ruff]; ruff comes with the test extra)
lint: $(STAMP)
	$(VENV)/bin/python -m ruff check .

# mypy on the packages [tool.mypy] in pyproject.toml lists, with check_untyped_defs (mypy comes with the test extra)
typecheck: $(STAMP)
	$(VENV)/bin/python -m mypy

bench: $(DEMO_STAMP)
	$(VENV)/bin/rayfronts bench world --json out/bench_world.json

clean-build:
	rm -rf build $(VENV)/.rayfronts-setup-* $(VENV)/.rayfronts-ext-key
