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

demo: $(STAMP)
	$(BIN)/recal demo

# One BLAS thread: Recal's matrices are small and a 2-core machine is shared (see service/cli.py).
test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q $(PYTEST_ARGS)

bench: $(STAMP)
	$(BIN)/python bench/identify.py

.PHONY: install demo test bench
