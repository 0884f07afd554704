# The two commands of the README: `make demo` and `make test`.
# Both create .venv if it is missing and install the project with the pinned versions of constraints.txt.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench papers docker-smoke clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml constraints.txt
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/aerocal demo

# the tests in two processes (the machine's two cores), a test file's tests in one of them: a module's fixtures
# (a Prefect server, the flights of a rendered test) are made once. Files in the order tests/conftest.py gives them
# (the longest first): pytest-xdist otherwise reorders them by their number of tests, which started the rendered
# flights (2 tests, 15 minutes) 21 minutes into the run
# OMP/OpenBLAS/MKL at one thread per test process: two processes on two cores, each with a BLAS pool of two
# threads that spin while they wait, had the whole run at 46 minutes; at one thread it took 22 (26 since the
# cluster, store-fault and campaign tests)
test: $(STAMP)
	$(BIN)/ruff check .
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
		$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=25

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python -m benchmarks

# the seed papers' set-ups simulated against their measured numbers (42 min on 2 cores when last run): the
# committed report studies/results/paper_setups.md, each study's own report, figures and numbers beside it
papers: $(STAMP)
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(BIN)/python -m studies.paper_setups --out studies/results

# the compose stack brought up for real (needs a Docker daemon; not part of `make test`)
docker-smoke: $(STAMP)
	$(BIN)/python docker/smoke.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
