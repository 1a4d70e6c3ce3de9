# ajtwin — every target creates/uses .venv, so a fresh clone needs nothing else.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-all bench docs docs-serve lint openfoam chromium postgresql clean screenshots

$(VENV): $(STAMP)

# Says what it installs and how big; pip shows each download with its progress bar.
$(STAMP): pyproject.toml
	@echo "install: ajtwin into $(VENV)/ — about 2.5 GB once installed, a few minutes (3 steps)"
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "install [1/3]: pip, upgraded"
	$(PY) -m pip install --quiet --upgrade pip
	@echo "install [2/3]: torch 2.13.0, CPU build (a 190 MB wheel, 750 MB installed) —"
	@echo "               first and from the exact pin, so nothing pulls a CUDA build"
	$(PY) -m pip install --progress-bar on torch==2.13.0
	@echo "install [3/3]: ajtwin and its libraries (JAX 380 MB, PyArrow 170 MB, Playwright"
	@echo "               165 MB, OpenCV 150 MB, SciPy, pandas, plotly, ...; the docs' MkDocs too:"
	@echo "               the suite builds the documentation site, tests/test_docs_site.py)"
	$(PY) -m pip install --progress-bar on -e '.[dev,docs]'
	touch $(STAMP)
	@echo "install: done — $$(du -sh $(VENV) | cut -f1) in $(VENV)/; the command: $(VENV)/bin/ajtwin"

.venv: $(STAMP)

# ajtwin's bytecode, brought up to date (a second when nothing changed): an editable install
# compiles none, and a Python that does not write bytecode (PYTHONDONTWRITEBYTECODE, common in
# containers) would otherwise compile every ajtwin module again in every command it starts
BYTECODE = $(PY) -m compileall -q src/ajtwin

# OpenFOAM v1912 from Debian, for the CFD macro-model; skipped when already present.
openfoam:
	@if [ -f /usr/share/openfoam/etc/bashrc ] && command -v blockMesh >/dev/null 2>&1 || [ -x /usr/bin/blockMesh ]; then \
		echo "openfoam: present"; \
	else \
		echo "openfoam: installing Debian package (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq openfoam >/dev/null; \
	fi

# Debian's chromium, driven by Playwright in the dashboard's browser tests (Playwright's own
# browser download is not possible here); skipped when already present.
chromium:
	@if [ -x /usr/bin/chromium ]; then \
		echo "chromium: present"; \
	else \
		echo "chromium: installing Debian package (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	fi

# Debian's PostgreSQL server, for the registry's tests on PostgreSQL (each test session starts a
# server of its own with initdb + pg_ctl in a temporary folder, as the `postgres` user when
# run as root: tests/conftest.py); skipped when already present.
postgresql:
	@if ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then \
		echo "postgresql: present"; \
	else \
		echo "postgresql: installing Debian package (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null; \
	fi

demo: $(STAMP)
	@$(BYTECODE)
	$(VENV)/bin/ajtwin demo

# one worker per core (the suite is mostly one-threaded); a test file stays on one worker, so
# its module fixtures (simulated prints, servers) are made once
TEST_WORKERS ?= auto

# a test running 30 s or longer is named every 30 s; the files that took longest last time
# start first (tests/suite_progress.py); the 15 slowest tests are listed at the end
test: $(STAMP) openfoam chromium postgresql
	@$(BYTECODE)
	AJTWIN_TEST_HEARTBEAT=30 $(PY) -m pytest -m "not slow" -q -n $(TEST_WORKERS) --dist loadfile --durations=15

# the slow tests include the develop study's generic Bayesian optimisation (the [study] extra)
STUDY_STAMP := $(VENV)/.installed-study

$(STUDY_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install --quiet -e '.[dev,study]'
	touch $(STUDY_STAMP)

test-all: $(STUDY_STAMP) openfoam chromium postgresql
	$(PY) -m pytest -q

BENCH_STAMP := $(VENV)/.installed-bench

$(BENCH_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install --quiet -e '.[dev,bench]'
	touch $(BENCH_STAMP)

# asv (asv.conf.json) in this environment; the results are filed under the current commit
# (.asv/results; `asv show`, `asv compare A B`, `asv publish`). BENCH_ARGS: more options,
# e.g. BENCH_ARGS='--bench bench_startup' or '--quick'.
BENCH_ARGS ?=
bench: $(BENCH_STAMP) chromium postgresql
	@$(BYTECODE)
	$(VENV)/bin/asv machine --yes >/dev/null
	$(VENV)/bin/asv run --python=same --set-commit-hash=$$(git rev-parse HEAD) --show-stderr $(BENCH_ARGS)
	# SQLite against PostgreSQL side by side in one run (a lab's registry on a server)
	$(PY) benchmarks/bench_store_backends.py

# Every page a person reads (the demo's report, a part report, the dashboard's pages) at
# 1400 px wide into build/screenshots/now/*.png, each checked for overflow, clipped text and
# empty boxes (problems.json). BEFORE=REV: also the same pages of another commit, into
# build/screenshots/REV/ (e.g. make screenshots BEFORE=main).
BEFORE ?=
screenshots: $(STAMP) chromium
	$(PY) scripts/screenshots.py --out build/screenshots/now
	$(if $(BEFORE),$(PY) scripts/screenshots.py --rev $(BEFORE) --out build/screenshots/$(BEFORE))

# The documentation site in site/ (open site/index.html; search needs it served: make docs-serve).
# Strict: a broken link or anchor, a page left out of the navigation or a docstring that does
# not render fails the build.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true $(VENV)/bin/mkdocs build --strict

DOCS_PORT ?= 8000
docs-serve: docs
	@echo "the documentation: http://127.0.0.1:$(DOCS_PORT)/index.html (Ctrl-C to stop)"
	$(PY) -m http.server --bind 127.0.0.1 --directory site $(DOCS_PORT)

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks scripts
	$(VENV)/bin/ruff format --check src tests benchmarks scripts

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache demo-output site
