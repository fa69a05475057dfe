# The two commands a newcomer needs: `make demo` and `make test`.
# Each sets up its own virtual environment on first use.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test bench bench-large fuzz eval-seneca lint clean

# The server's runtime dependencies install at the versions docker/requirements.lock pins (the
# image's), so a fresh checkout tests what the image runs, whatever PyPI released since.
$(STAMP): pyproject.toml docker/requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c docker/requirements.lock -e '.[dev]'
	touch $(STAMP)

## demo: synthetic world -> server on embedded defaults -> map over HTTP -> replay -> table
demo: $(STAMP)
	$(BIN)/vloc demo

## test: the whole test suite (PostgreSQL/Redis tests skip when those are absent)
test: $(STAMP)
	$(BIN)/python -m pytest -q

## bench: stage timings and the paper experiments (long; writes bench/results/)
bench: $(STAMP)
	$(BIN)/python bench/run_all.py

## bench-large: a 50,000-image UAV map built through the service: build throughput, step
## times, worker memory, database size (hours on two cores; resumable; writes
## bench/results/large_map.md, work files under bench/.cache/large-map/)
bench-large: $(STAMP)
	$(BIN)/python bench/bench_large_map.py

## fuzz: Schemathesis with every check against a real server (writes bench/results/fuzz.txt)
fuzz: $(STAMP)
	$(BIN)/python bench/fuzz.py --max-examples 200 --out bench/results/fuzz.txt

## eval-seneca: the real-data evaluation (needs ../shared/datasets/seneca-uav)
eval-seneca: $(STAMP)
	$(BIN)/python bench/eval_seneca.py

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
