# Two entry points: `make serve` (install the runtime, serve the bundled model) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
HOST ?= 127.0.0.1
PORT ?= 8080

.PHONY: serve test test-all lint dist install-serve install-dev install-browser clean

# uv installs the extras: the same pinned requirements, resolved and unpacked in parallel (docs/decisions/0098), and
# compiled to bytecode as pip compiles them: without it every Python process compiles the modules it imports again
# where the environment sets PYTHONDONTWRITEBYTECODE (docs/decisions/0099).
# uv reads no pip configuration (an index mirror, find-links, certificates set for pip only; uv's own are UV_*
# variables), so where it cannot install them pip does. pip stays in the venv: it installs torch (below) and runs the
# docs' commands.
UV ?= uv==0.9.30

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(BIN)/uv: $(BIN)/python
	$(BIN)/pip install -q "$(UV)"

install-serve: $(BIN)/uv
	$(BIN)/uv pip install -q --compile-bytecode --python $(BIN)/python -e ".[serve]" || $(BIN)/pip install -q -e ".[serve]"

# torch first, from PyTorch's CPU index: PyPI's Linux torch wheel is the CUDA build (it requires cuda-toolkit and
# nvidia-* packages). The extras then find it installed (TORCH is pyproject.toml's pin; a test checks they agree).
# `make test TORCH_INDEX=<another PyTorch index>` installs another build (a CUDA one). pip, not uv, installs it: pip
# also reads the machine's pip configuration (a local wheel through find-links) and goes on where an index cannot be
# reached; uv stops there.
TORCH ?= torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu

install-dev: $(BIN)/uv
	$(BIN)/pip install -q --no-deps --index-url $(TORCH_INDEX) "$(TORCH)"
	$(BIN)/uv pip install -q --compile-bytecode --python $(BIN)/python -e ".[train,dev]" || $(BIN)/pip install -q -e ".[train,dev]"

# Headless Chromium and its driver for the page's browser test (Debian packages; quick when present), and axe-core
# (npm, into $(VENV)/node_modules) for its accessibility check. Without root or apt, or npm, those tests skip and say why.
AXE_CORE ?= 4.11.0
install-browser:
	@if command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
			chromium chromium-driver >/dev/null; \
	else echo "install-browser: chromium + chromium-driver absent and not root with apt; the browser tests will skip"; fi
	@if [ -f $(VENV)/node_modules/axe-core/package.json ] && grep -q '"version": "$(AXE_CORE)"' \
		$(VENV)/node_modules/axe-core/package.json; then :; \
	elif command -v npm >/dev/null 2>&1; then \
		npm install -s --prefix $(VENV) --no-save --no-package-lock --no-audit --no-fund axe-core@$(AXE_CORE) \
			|| echo "install-browser: npm could not install axe-core; the page's accessibility test will skip"; \
	else echo "install-browser: npm absent, axe-core not installed; the page's accessibility test will skip"; fi

serve: install-serve
	$(BIN)/mfgnet serve --host $(HOST) --port $(PORT)

# Two pytest workers, one test file each at a time (module fixtures such as servers stay per file): the suite waits
# on servers, subprocesses and a browser much of the time, so two workers on two cores finish it about 1.35x sooner.
# Timing-sensitive checks (marked serial: signals, deadlines, load, timing ratios) then run alone, collected from
# the files that mark them only (collecting every file takes ~15 s; with none found pytest collects them all).
SERIAL_FILES = $(shell grep -rlE --include='test_*.py' 'mark\.serial' tests | sort)
# The tests start many Python processes (servers, command lines, workers): they may write the checkout's bytecode
# (__pycache__, ignored by git) whatever PYTHONDONTWRITEBYTECODE says, so each process does not compile it again.
PYTEST := PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest
test: install-dev install-browser
	$(PYTEST) -q -n 2 --dist loadfile -m "not slow and not serial"
	$(PYTEST) -q -m "serial and not slow" $(SERIAL_FILES)

test-all: install-dev install-browser
	$(PYTEST) -q -n 2 --dist loadfile -m "not serial"
	$(PYTEST) -q -m "serial" $(SERIAL_FILES)

lint: install-dev
	$(BIN)/ruff check .

# The sdist, and the wheel built from it, into dist/, checked as the package index checks them. build/ and the
# egg-info go first: setuptools reads an old egg-info's SOURCES.txt back into a new sdist.
dist: install-dev
	rm -rf build dist *.egg-info
	$(BIN)/python -m build --outdir dist .
	$(BIN)/twine check --strict dist/*

clean:
	rm -rf build dist *.egg-info .pytest_cache .ruff_cache
