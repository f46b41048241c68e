# `make demo` and `make test` work on a fresh machine: they create .venv themselves.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
TNNC   := $(VENV)/bin/tnnc
STAMP  := $(VENV)/.installed
JOBS   ?= 2

.PHONY: venv demo test test-all lint bench check clean browser

# pip installs without compiling each file to bytecode as it unpacks (one core); compileall then compiles the
# installed packages on every core, their test suites left out (`/test/`, `/tests/`; not `torch/testing`, which
# torch imports). Measured (2026-12-05, 2 cores, fresh venvs one after the other): 36.8 against 55.6 s and 55.6
# against 72.1 s, the same imports in the same time after (the bytecode is written here: environments that set
# PYTHONDONTWRITEBYTECODE never write it at import).
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-compile torch==2.13.0
	$(PY) -m pip install -q --no-compile -e '.[dev,fleet]'
	$(PY) -m compileall -q -j 0 -x '/tests?/' "$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" \
	  > /dev/null 2>&1 || true  # as pip: a file that does not compile (torch ships Python 3.12 syntax) is left as is
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(TNNC) demo

check: $(STAMP)
	$(TNNC) check networks/*/*.thn

# The fast suite (CI runs this): lint (ruff), the layering of the packages (import-linter: see pyproject.toml),
# then the tests; slow training/diagnosis tests have fast variants that run here.
# Headless Chromium from Debian's packages, for the browser tests of the HTML reports (tests/test_reports_in_browser.py
# skip without it). Installed with apt-get where this runs as root; elsewhere the command to run is printed.
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium) \
	      >/dev/null 2>&1 || echo "warning: could not install chromium; the browser tests will be skipped"; \
	  else echo "note: install chromium (sudo apt-get install chromium) to run the browser tests"; fi; }

# --dist worksteal: a worker that runs out of tests takes some of the other's, so the run does not end on one worker
# finishing a long queue alone (both workers ended within 6 s of each other, 2026-11-28).
test: $(STAMP) lint browser
	$(PY) -m pytest -q -n $(JOBS) --dist worksteal -m "not slow" --durations=25 tests

lint: $(STAMP)
	$(PY) -m ruff check tnn_dsl tests benchmarks examples
	$(VENV)/bin/lint-imports

test-all: $(STAMP) browser
	$(PY) -m pytest -q -n $(JOBS) --dist worksteal tests

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

clean:
	rm -rf $(VENV) build dist .pytest_cache
