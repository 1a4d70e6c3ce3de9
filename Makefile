# ajtwin — every target creates/uses .venv, so a fresh clone needs nothing else.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-all bench lint openfoam chromium postgresql clean

$(VENV): $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first, from the exact pin (local CPU wheel), so nothing pulls a CUDA build
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

.venv: $(STAMP)

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
	$(VENV)/bin/ajtwin demo

# one worker per core (the suite is mostly one-threaded); a test file stays on one worker, so
# its module fixtures (simulated prints, servers) are made once
TEST_WORKERS ?= auto

test: $(STAMP) openfoam chromium postgresql
	$(PY) -m pytest -m "not slow" -q -n $(TEST_WORKERS) --dist loadfile

test-all: $(STAMP) openfoam chromium postgresql
	$(PY) -m pytest -q

BENCH_STAMP := $(VENV)/.installed-bench

$(BENCH_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install --quiet -e '.[dev,bench]'
	touch $(BENCH_STAMP)

bench: $(BENCH_STAMP) chromium postgresql
	$(PY) benchmarks/run_all.py

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks scripts
	$(VENV)/bin/ruff format --check src tests benchmarks scripts

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache demo-output
