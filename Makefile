# Every target works on a fresh machine with Python 3.11 and pip: `install` builds .venv first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(BIN)/arena serve --demo

test: install
	$(BIN)/python -m pytest -q

lint: install
	$(BIN)/ruff check arena tests
	$(BIN)/ruff format --check arena tests
	$(BIN)/mypy

bench: install
	$(BIN)/arena bench

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
