# asynhdr: two commands. `make demo` and `make test` set up .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
OUT    ?= out
# test workers (pytest-xdist): the suite is many small cases, so two processes keep two
# cores busy; TEST_WORKERS=0 runs it in this process
TEST_WORKERS ?= 2

.PHONY: demo test bench lint typecheck clean setup

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $@

setup: $(VENV)/.installed

demo: $(VENV)/.installed
	$(VENV)/bin/asynhdr demo --out $(OUT)/demo

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check src tests benchmarks

typecheck: $(VENV)/.installed
	$(VENV)/bin/mypy

test: $(VENV)/.installed lint typecheck
	$(PY) -m pytest -q -n $(TEST_WORKERS)

bench: $(VENV)/.installed
	$(PY) benchmarks/run.py --out $(OUT)/bench

clean:
	rm -rf $(OUT) .pytest_cache .mypy_cache .ruff_cache
