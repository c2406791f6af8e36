# Two entry points: `make run` (the workflow on the embedded demo) and `make test`.
# Each creates .venv and installs the pinned dependencies on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(abspath $(VENV))/bin
STAMP := $(VENV)/.installed-$(shell cksum < pyproject.toml | cut -d' ' -f1)
CORES ?= 2

.PHONY: install run paper test lint clean

# The pose solver's compiled cores are rebuilt when their sources change.
$(STAMP): pyproject.toml setup.py dmais_pipe/pose/_kernels.pyx dmais_pipe/pose/_refine.pyx dmais_pipe/pose/_small.pxd
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	rm -f $(VENV)/.installed-* && touch $@

install: $(STAMP)

run: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/config.yaml

paper: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/paper.yaml

test: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/python -m pytest -q

lint: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/snakemake --lint --configfile config/config.yaml

clean:
	rm -rf results logs .snakemake data
