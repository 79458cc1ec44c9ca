# Two commands on a fresh machine: `make demo` and `make test`. Each creates .venv if
# missing and installs what it needs (torch first, pinned by constraints.txt).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# RUNS=N: every scenario of the demo with N Monte Carlo runs (default: each scenario's own)
RUNS ?=
OUT ?= reports
# DEVICES=N: processes that share each scenario's estimators in `make demo` (difffilter-eval
# --devices; the same numbers as one process). Default 2 on a machine with 2 CPUs or more:
# 1.33x faster than one process on the 2-core machine (docs/timings.md).
DEVICES ?= $(shell [ "$$(nproc 2>/dev/null || echo 1)" -ge 2 ] && echo 2 || echo 1)
# TEST_JOBS=N: pytest worker processes (pytest-xdist; each on one intra-op thread, a file's
# tests in one worker so that its module fixtures are built once). Default: one per CPU, at
# most 8; TEST_JOBS=0 runs the suite in this process.
TEST_JOBS ?= auto
PYTEST_ARGS := -q -n $(TEST_JOBS) --maxprocesses 8 --dist loadfile
# The suite keeps its compiled files (pytest's rewritten test modules and the package's
# bytecode, in the git-ignored __pycache__ folders) even where PYTHONDONTWRITEBYTECODE is
# set: otherwise every worker compiles them all again, about 10 s of each process's start
# on the 2-core machine (collection 19.7 s against 8.7-9.8 s once they are kept, 2026-12-03)
KEEP_BYTECODE := env -u PYTHONDONTWRITEBYTECODE

.PHONY: demo test test-slow test-all test-min bench lint venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -c constraints.txt torch==2.13.0
	$(PY) -m pip install -q -c constraints.txt -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/difffilter-eval all --out $(OUT) --devices $(DEVICES) $(if $(RUNS),--runs $(RUNS),)

# `make test` leaves out the `slow` group (tests/conftest.py: end-to-end command-line runs,
# trainings, multi-process and many-run statistical checks); `make test-slow` runs it;
# `make test-all` runs everything; CI (.ci/run) runs both groups.
test: $(STAMP)
	$(PY) -m ruff check .
	$(KEEP_BYTECODE) $(PY) -m pytest $(PYTEST_ARGS) -m "not slow"

test-slow: $(STAMP)
	$(KEEP_BYTECODE) $(PY) -m pytest $(PYTEST_ARGS) -m slow

test-all: $(STAMP)
	$(PY) -m ruff check .
	$(KEEP_BYTECODE) $(PY) -m pytest $(PYTEST_ARGS)

# The declared minimum versions (constraints-min.txt) in a venv of their own
VENV_MIN := .venv-min
test-min:
	test -x $(VENV_MIN)/bin/python || $(PYTHON) -m venv $(VENV_MIN)
	$(VENV_MIN)/bin/python -m pip install -q -c constraints-min.txt torch==2.13.0 "setuptools>=77,<81"
	$(VENV_MIN)/bin/python -m pip install -q -c constraints-min.txt -e ".[dev]"
	$(KEEP_BYTECODE) $(VENV_MIN)/bin/python -m pytest $(PYTEST_ARGS)

# the `bench` extra: the peers section 8 times beside ours (torch-kf; torch stays pinned)
BENCH_STAMP := $(VENV)/.bench-installed
$(BENCH_STAMP): $(STAMP)
	$(PY) -m pip install -q -c constraints.txt -e ".[dev,bench]"
	touch $(BENCH_STAMP)

bench: $(BENCH_STAMP)
	$(PY) benchmarks/bench.py

lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

clean:
	rm -rf $(VENV) $(VENV_MIN) build *.egg-info
