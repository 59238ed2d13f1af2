# Two commands for a newcomer: `make run` (the main job) and `make test` (lint + tests).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint bench docs docs-serve results

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/cfbci session

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/lint-imports

test: lint docs
	$(BIN)/pytest -n 2 -q

bench: $(STAMP)
	$(BIN)/cfbci bench update

# The documentation site (mkdocs.yml): built strict, so that a broken link, anchor or page, or
# a generated reference part that fails, fails the build (and `make test`); into site/.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

docs-serve: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs serve

# Re-run every results page's commands and rewrite their tables (hours on 2 cores; not in
# `make test`). One page: `make results PAGES=docs/results/sessions.md`.
results: $(STAMP)
	$(BIN)/python tools/results.py $(PAGES)
