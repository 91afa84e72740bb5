# TopoFusion: `make demo` and `make test` do all set-up on a fresh machine.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# Two installs into the one venv, each with its stamp (redone when a pyproject changes):
#   demo: the runtime and the lab (lab/: simulator, scenarios, evaluation), no test toolchain;
#   test: the runtime with its test extra, and the lab (the tests use the simulator).
# Each installs the runtime and the lab in one pip command, so that the lab's requirement
# `topofusion` resolves to this checkout.
DEMO_STAMP := $(VENV)/.installed-demo-stamp
TEST_STAMP := $(VENV)/.installed-test-stamp
PYPROJECTS := pyproject.toml lab/pyproject.toml
LINTED := service tests bench lab
# Two test processes (pytest-xdist): the end-to-end tests mostly wait, so two halve the wall
# time on a 2-core machine; every test uses its own free ports and processes.  `-n 0` runs
# them in one process.  A file's tests go to one process (its module fixtures are made once),
# the files with `slow` tests first (tests/conftest.py), so that both processes end together.
PYTEST_ARGS ?= -n 2 --dist loadfile

.PHONY: install install-demo demo run test lint imports typecheck unit bench evaluate schemas clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(DEMO_STAMP): $(PYPROJECTS) | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e . -e lab
	touch $(DEMO_STAMP)

$(TEST_STAMP): $(PYPROJECTS) | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]" -e lab
	touch $(TEST_STAMP)

install-demo: $(DEMO_STAMP)

install: $(TEST_STAMP) ## development install: runtime, test extra, lab

demo: install-demo ## the service plus its simulator on an embedded Zenoh peer (Ctrl-C stops)
	$(BIN)/topofusion demo

run: install-demo
	$(BIN)/topofusion run

lint: install
	$(BIN)/ruff check $(LINTED)
	$(BIN)/ruff format --check $(LINTED)

imports: install ## the import rules of the house (pyproject.toml [tool.importlinter])
	$(BIN)/lint-imports

typecheck: install
	$(BIN)/mypy

unit: install
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# The type check runs beside the suite (two test processes kept two cores 86 % busy, measured):
# its report comes after the tests', and either failing fails the target.
test: lint imports ## installs, lints, checks imports and types, runs the whole suite
	@$(BIN)/mypy > $(VENV)/mypy.log 2>&1 & types=$$!; \
	$(BIN)/python -m pytest $(PYTEST_ARGS); tests=$$?; \
	wait $$types; typed=$$?; echo "$(BIN)/mypy"; cat $(VENV)/mypy.log; \
	exit $$(( tests != 0 || typed != 0 ))

bench: install
	for b in bench/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# Into docs/evaluation, where docs/results.md links the report from (the command's own default,
# ./evaluation, is for ad-hoc runs and is gitignored).
evaluate: install-demo
	$(BIN)/topofusion evaluate --out docs/evaluation

schemas: install-demo
	$(BIN)/topofusion schemas --out schemas

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
