# The two commands a newcomer needs: `make demo` and `make test`.
# Each sets up its own virtual environment on first use.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
PIP    := $(BIN)/python -m pip --quiet --quiet --disable-pip-version-check
# Two stamps: the runtime (what `make demo` needs) and, on top of it, the dev extra (pytest,
# Playwright, Schemathesis, Ray: what the tests and benchmarks need). Either order works:
# `make test` after `make demo` adds the dev extra; `make demo` after `make test` has all.
RUNTIME := $(VENV)/.runtime-stamp
# what `make demo` runs imports these (and, through them, most of what it needs)
WARM    := vloc.clients.cli vloc.clients.demo vloc.clients.replay vloc.app.main vloc.app.tasks \
           vloc.workers.engine.pool vloc.workers.engine.worker vloc.workers.core.mapbuild \
           vloc.workers.core.localisers vloc.workers.core.evaluation.report matplotlib.pyplot
IMPORT_ALL := import importlib, sys; [importlib.import_module(m) for m in sys.argv[1:]]
DEV     := $(VENV)/.dev-stamp

.PHONY: demo test bench bench-large fuzz eval-seneca lint clean

# The server's runtime dependencies install at the versions docker/requirements.lock pins (the
# image's), so a fresh checkout tests what the image runs, whatever PyPI released since.
$(RUNTIME): pyproject.toml docker/requirements.lock
	@echo "setting up $(VENV): the runtime dependencies (first run only, a few minutes)"
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@$(PIP) install --upgrade pip
	@$(PIP) install --no-compile -c docker/requirements.lock -e .
	@# bytecode for what the server, its workers and the CLI import, not for every module of
	@# every dependency (a sixth of the environment): Python writes it on first import, but
	@# where it may not (PYTHONDONTWRITEBYTECODE) each process would compile SciPy, FastAPI
	@# and the rest from source every time
	@env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -c '$(IMPORT_ALL)' $(WARM)
	@touch $@

$(DEV): $(RUNTIME)
	@echo "setting up $(VENV): the test tools (the dev extra; first run only)"
	@$(PIP) install -c docker/requirements.lock -e '.[dev]'
	@# the tests import much more than the service: all of it as bytecode here
	@$(BIN)/python -m compileall -q -j 0 $(VENV)/lib >/dev/null || true
	@touch $@

## demo: synthetic world -> server on embedded defaults -> map over HTTP -> replay -> table
demo: $(RUNTIME)
	@$(BIN)/vloc demo

## test: the whole test suite (PostgreSQL/Redis tests skip when those are absent), run by
## TEST_WORKERS processes in parallel; tests sharing an app, a server or Ray stay together
TEST_WORKERS ?= 2
test: $(DEV)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

## bench: stage timings and the paper experiments (long; writes bench/results/)
bench: $(DEV)
	$(BIN)/python bench/run_all.py

## bench-large: a 50,000-image UAV map built through the service: build throughput, step
## times, worker memory, database size (hours on two cores; resumable; writes
## bench/results/large_map.md, work files under bench/.cache/large-map/)
bench-large: $(DEV)
	$(BIN)/python bench/bench_large_map.py

## fuzz: Schemathesis with every check against a real server (writes bench/results/fuzz.txt)
fuzz: $(DEV)
	$(BIN)/python bench/fuzz.py --max-examples 200 --out bench/results/fuzz.txt

## eval-seneca: the real-data evaluation (needs ../shared/datasets/seneca-uav)
eval-seneca: $(DEV)
	$(BIN)/python bench/eval_seneca.py

lint: $(DEV)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
