# Two entry points: `make serve` (install the runtime, serve the bundled model) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
HOST ?= 127.0.0.1
PORT ?= 8080

.PHONY: serve test test-all lint install-serve install-dev clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

install-serve: $(BIN)/python
	$(BIN)/pip install -q -e ".[serve]"

install-dev: $(BIN)/python
	$(BIN)/pip install -q -e ".[train,dev]"

serve: install-serve
	$(BIN)/mfgnet serve --host $(HOST) --port $(PORT)

test: install-dev
	$(BIN)/python -m pytest -q

test-all: install-dev
	$(BIN)/python -m pytest -q -m "slow or not slow"

lint: install-dev
	$(BIN)/ruff check .

clean:
	rm -rf build dist *.egg-info .pytest_cache .ruff_cache
