# Every target works on a fresh machine with Python 3.11 and pip: `install` builds .venv first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

# The dashboard: built with the machine's Node.js and npm (packages from the npm registry).
UI := arena/dashboard
UI_BUILT := $(UI)/dist/index.html
UI_MODULES := $(UI)/node_modules/.package-lock.json
UI_SOURCES := $(UI)/build.mjs $(UI)/index.html $(UI)/style.css $(wildcard $(UI)/src/*.js)
# The browser tests drive Debian's chromium (Playwright cannot download its own browser here).
CHROMIUM := /usr/bin/chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: install ui browser run fleet demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

$(UI_MODULES): $(UI)/package.json $(UI)/package-lock.json
	cd $(UI) && npm ci --no-audit --no-fund --loglevel=error

$(UI_BUILT): $(UI_MODULES) $(UI_SOURCES)
	cd $(UI) && node build.mjs

ui: $(UI_BUILT)

browser:
	@test -x $(CHROMIUM) || { $(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq chromium >/dev/null; }

run: install ui
	$(BIN)/arena serve --demo

# NODES fleet nodes on this machine, one per core (specs/fleet.md): n0 on :8080 with the demo
# robot, nK on :808K; Zenoh on tcp/127.0.0.1:7447+K. Ctrl-C stops them all.
NODES ?= 2
fleet: install ui
	@trap 'kill 0' EXIT; \
	for k in $$(seq 1 $$(($(NODES) - 1))); do \
		$(BIN)/arena serve --node n$$k --port $$((8080 + k)) --recordings-dir recordings/n$$k \
			--fleet-listen tcp/127.0.0.1:$$((7447 + k)) --fleet-connect tcp/127.0.0.1:7447 & \
	done; \
	$(BIN)/arena serve --node n0 --port 8080 --demo --recordings-dir recordings/n0 \
		--fleet-listen tcp/127.0.0.1:7447

test: install ui browser
	$(BIN)/python -m pytest -q

lint: install
	$(BIN)/ruff check arena tests
	$(BIN)/ruff format --check arena tests
	$(BIN)/mypy
	$(BIN)/deptry .

bench: install
	$(BIN)/arena bench

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis $(UI)/node_modules $(UI)/dist
