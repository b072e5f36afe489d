# Every target works on a fresh machine with Python 3.11 and pip: each builds .venv first.
# `make run` installs only what serving needs (the runtime packages); `make test` and `make lint`
# add everything else (`.[dev]`: the extras, LeRobot with torch, the test tools). Each install
# has its own stamp, so `make test` after `make run` adds the rest to the same .venv.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
RUNTIME := $(VENV)/.installed-runtime
DEV := $(VENV)/.installed-dev
FLEET := $(VENV)/.installed-fleet
# `make run PORT=9000`; `make fleet PORT=9000` puts node k on PORT+k (Zenoh on ZENOH_PORT+k).
PORT ?= 8080
ZENOH_PORT ?= 7447

# The dashboard: built with the machine's Node.js and npm (packages from the npm registry).
UI := arena/dashboard
UI_BUILT := $(UI)/dist/index.html
UI_MODULES := $(UI)/node_modules/.package-lock.json
UI_SOURCES := $(UI)/build.mjs $(UI)/index.html $(UI)/style.css $(wildcard $(UI)/src/*.js)
# The browser tests drive Debian's chromium (Playwright cannot download its own browser here).
CHROMIUM := /usr/bin/chromium
# The physics twin's cameras render headless through Debian's OSMesa (specs/learning.md).
OSMESA := /usr/lib/$(shell uname -m)-linux-gnu/libOSMesa.so.8
comma := ,
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: install install-dev ui browser osmesa run fleet demo test lint bench mutants compat package clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(RUNTIME): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $(RUNTIME)

$(DEV): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(DEV) $(RUNTIME) $(FLEET)

$(FLEET): $(RUNTIME)
	$(BIN)/python -m pip install --quiet -e '.[fleet]'
	touch $(FLEET)

install: $(RUNTIME)

install-dev: $(DEV)

$(UI_MODULES): $(UI)/package.json $(UI)/package-lock.json
	cd $(UI) && npm ci --no-audit --no-fund --loglevel=error

$(UI_BUILT): $(UI_MODULES) $(UI_SOURCES)
	cd $(UI) && node build.mjs

ui: $(UI_BUILT)

browser:
	@test -x $(CHROMIUM) || { $(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq chromium >/dev/null; }

osmesa:
	@test -e $(OSMESA) || { $(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq libosmesa6 >/dev/null; }

run: install ui
	$(BIN)/arena serve --demo --sim-leader --port $(PORT)

# NODES fleet nodes on this machine, one per core (specs/fleet.md): n0 on PORT (8080) with the
# demo robot, nK on PORT+K; Zenoh on tcp/127.0.0.1:ZENOH_PORT+K. Ctrl-C stops them all.
NODES ?= 2
fleet: $(FLEET) ui
	@trap 'kill 0' EXIT; \
	for k in $$(seq 1 $$(($(NODES) - 1))); do \
		$(BIN)/arena serve --node n$$k --port $$(($(PORT) + k)) --recordings-dir recordings/n$$k \
			--fleet-listen tcp/127.0.0.1:$$(($(ZENOH_PORT) + k)) \
			--fleet-connect tcp/127.0.0.1:$(ZENOH_PORT) & \
	done; \
	$(BIN)/arena serve --node n0 --port $(PORT) --demo --recordings-dir recordings/n0 \
		--fleet-listen tcp/127.0.0.1:$(ZENOH_PORT)

test: install-dev ui browser osmesa
	$(BIN)/python -m pytest -q -rs

lint: install-dev
	$(BIN)/ruff check arena tests tools examples
	$(BIN)/ruff format --check arena tests tools examples
	$(BIN)/mypy
	$(BIN)/deptry .

bench: install-dev
	$(BIN)/arena bench

# Against LeRobot 0.6: tools/compat.sh builds its Python in .compat/ (Debian 13's, LeRobot 0.6.1
# in a virtualenv: ~5 GB and a few minutes, once; kept until `make clean`), then the compat
# tests run policies and workers of both LeRobots (tests/test_compat.py). Not part of `test`.
compat: install-dev osmesa
	bash tools/compat.sh
	$(BIN)/python -m pytest -q -rs -m compat tests/test_compat.py

# The sdist and the wheel in dist/, carrying the built dashboard: `pip install dist/arena-*.whl`
# needs no Node and no checkout (README, "Deploy").
package: install-dev ui
	$(BIN)/python -m build --outdir dist .

# Mutation testing of the safety-critical modules (specs/mutation.md). Not part of `test`: it
# takes long. MUTATE=safety,motion runs some modules only (names in tools/mutants.py).
MUTATE ?=
mutants: install-dev
	nice -n 19 $(BIN)/python tools/mutants.py $(subst $(comma), ,$(MUTATE))

clean:
	rm -rf $(VENV) .compat mutants .pytest_cache .mypy_cache .ruff_cache .hypothesis $(UI)/node_modules $(UI)/dist
