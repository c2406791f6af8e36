# Two entry points: `make run` (the workflow on the embedded demo) and `make test`.
# Each creates .venv and installs the dependencies, locked by constraints.txt, on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(abspath $(VENV))/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml constraints.txt | cksum | cut -d' ' -f1)
CORES ?= 2

.PHONY: install run paper test lint clean

# The pose solver's compiled cores are rebuilt when their sources change.
$(STAMP): pyproject.toml constraints.txt setup.py dmais_pipe/pose/_kernels.pyx dmais_pipe/pose/_refine.pyx dmais_pipe/pose/_small.pxd
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	PIP_CONSTRAINT=$(abspath constraints.txt) $(BIN)/python -m pip install --quiet -e '.[test]'
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
