# Two commands for a fresh machine with only Python 3.11: `make demo`, `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test lint bench results docs clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed-run: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@ $(VENV)/.installed-run

demo: $(VENV)/.installed-run
	$(BIN)/posecast demo

# Two workers (pytest-xdist): most tests wait on sockets and timers, not the CPU, so
# two halve the wall time on a 2-core machine. Tests that build or drive the JS
# bundle and Chromium share a group (tests/conftest.py): one worker runs them in turn.
# Bytecode is cached even where the caller's environment says not to
# (PYTHONDONTWRITEBYTECODE): the suite starts many `posecast` processes (relays, bots,
# attackers), each of which would compile the sources again (13 % of the CPU of
# test_interrupt + test_bot_session_end from a clean tree). The workers take the
# longest groups first, in the order tests/conftest.py puts them (no reordering).
test: $(VENV)/.installed-test
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -n 2 --dist loadgroup --no-loadscope-reorder --durations=25

# mypy reads modules from files, not through the install's folder mapping: it checks
# a tree of links laid out as the installed package (posecast/server -> server/, ...).
FOLDERS := server client protocol interp recorder scenarios
TYPECHECK := build/typecheck

lint: $(VENV)/.installed-test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	rm -rf $(TYPECHECK) && mkdir -p $(TYPECHECK)/posecast
	for e in posecast/*; do ln -s ../../../$$e $(TYPECHECK)/posecast/; done
	for d in $(FOLDERS); do ln -s ../../../$$d $(TYPECHECK)/posecast/$$d; done
	cd $(TYPECHECK) && ../../$(BIN)/mypy --config-file ../../pyproject.toml

bench: $(VENV)/.installed-test
	$(BIN)/posecast bench interp

# Regenerate every published result (docs/results/, the tables of docs/lab/results.md and
# docs/lab/results-recording.md) with the current code; prints which outputs changed.
# Uses the full trace sets bundled in the package; 12-20 minutes. Not part of `test`.
results: $(VENV)/.installed-run
	nice -n 5 $(BIN)/python -m posecast.results

$(VENV)/.installed-docs: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[docs]'
	touch $@ $(VENV)/.installed-run

# The documentation site into site/ (mkdocs-material); any warning fails the build. The
# Reference pages are written from the code by docs/hooks/reference.py as it builds.
docs: $(VENV)/.installed-docs
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

clean:
	rm -rf $(VENV) build site *.egg-info
