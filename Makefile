# Two entry points (README): `make demo` runs the main job, `make test` runs the tests.
# Both create .venv and install the project into it first, so a fresh machine needs nothing else.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,fleet]'
	touch $(STAMP)

install: $(STAMP)

# `make demo HOST=127.0.0.3 PORT=8080`: the simulated cell's loopback address and the service's
# port (defaults: recal demo's, 127.0.0.2 and 8000).
HOST ?= 127.0.0.2
PORT ?= 8000
demo: $(STAMP)
	$(BIN)/recal demo --host $(HOST) --port $(PORT)

# The browser tests (tests/web) drive Debian's Chromium through Playwright (never `playwright
# install`): installed here when it is missing and this is Debian as root; otherwise those tests
# are skipped, and pytest's summary says why.
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    apt-get update -qq && apt-get install -y -qq chromium; \
	  else \
	    echo "make: no chromium here; the browser tests will be skipped (as root on Debian: apt-get install chromium)"; \
	  fi; }

# One BLAS thread: Recal's matrices are small and a 2-core machine is shared (see service/cli.py).
# The PostgreSQL tests run when RECAL_TEST_POSTGRES_URL names a server where they may create and
# drop databases (`make test RECAL_TEST_POSTGRES_URL=postgresql+psycopg://postgres@127.0.0.1:5432/postgres`;
# .ci/run sets it); without it they are skipped, and pytest's summary says so.
# Two workers (pytest-xdist: the simulated cells mostly wait on sockets and simulated time), then
# the few tests marked `serial` (one restarts PostgreSQL) alone. Each test file runs whole in one
# worker, in its order (--dist loadfile): module-scoped fixtures (a simulated cell, a CAN
# gateway) see their tests in the order they were written for.
# The serial tests run whatever the parallel run gave, and `make test` fails when either failed
# (the parallel run's status first). pytest's 5, "no tests collected", is a pass for the serial run
# (PYTEST_ARGS may name files without serial tests).
test: $(STAMP) browser
	@parallel=0; serial=0; \
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not serial" $(PYTEST_ARGS) || parallel=$$?; \
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -m serial $(PYTEST_ARGS) || serial=$$?; \
	if [ $$serial = 5 ]; then serial=0; fi; \
	if [ $$parallel != 0 ]; then echo "make test: the parallel run failed (pytest status $$parallel)" >&2; exit $$parallel; fi; \
	if [ $$serial != 0 ]; then echo "make test: the serial run failed (pytest status $$serial)" >&2; exit $$serial; fi

# The linter and the formatter (ruff, configured in pyproject.toml): clean on the whole tree; the
# type checker (mypy, configured there too) on calibration/, drivers/ and the service/ modules
# its `files` lists.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/python bench/identify.py

.PHONY: install demo test bench browser lint
