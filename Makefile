# The two commands: `make demo` (the main job) and `make test`.
# Both create .venv with the machine's python3 when it is missing and install the project into it.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: demo test test-slow test-all bench lint results clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[all]'
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[all,test]'
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/twin demo

# The fast tests on 2 workers (pytest-xdist; a test file's tests stay on one worker, so its module fixtures are
# built once): every test is isolation-safe (127.0.0.1 on ephemeral ports, tmp_path, numba's and the lab
# calibration's caches written atomically). TEST_WORKERS=0 runs them in this one process. `twin warm-up` first
# compiles the kernels of live and replay once (a cold cache: about a minute), so that no test streaming in
# real time compiles on its first frames and the workers do not compile the same kernels twice.
TEST_WORKERS ?= 2

test: $(VENV)/.installed-test
	$(BIN)/ruff check .
	$(BIN)/twin warm-up
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

test-slow: $(VENV)/.installed-test
	$(BIN)/python -m pytest -q -m slow $(PYTEST_ARGS)

test-all: $(VENV)/.installed-test
	$(BIN)/python -m pytest -q -m '' $(PYTEST_ARGS)

bench: $(VENV)/.installed
	$(BIN)/twin bench

# README's results tables: rerun every command they cite (tens of minutes of physics), keep their JSON in
# docs/results/ and rewrite the tables (scenarios/results_tables.py; tests/test_readme.py checks they match)
results: $(VENV)/.installed
	$(BIN)/python -m scenarios.results_tables --rerun --write README.md

lint: $(VENV)/.installed-test
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
