# Flash-Mono: `make demo` runs the main job, `make test` runs the whole test suite.
# Both create .venv and install everything on first use.
# PIP_FLAGS: extra pip options, e.g. PIP_FLAGS="--extra-index-url https://download.pytorch.org/whl/cpu" for the CPU
# build of torch where no local wheel provides it (PyPI's default torch wheel brings the CUDA libraries).
PYTHON ?= python3
PIP_FLAGS ?=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install test demo bench lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q $(PIP_FLAGS) -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q -rs tests

demo: $(STAMP)
	$(BIN)/flashmono demo

bench: $(STAMP)
	$(BIN)/python -m bench

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/lint-imports

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
