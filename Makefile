# Two entry points: `make run` (the workflow on the embedded demo) and `make test`.
# Each creates .venv and installs the dependencies, locked by constraints.txt, on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(abspath $(VENV))/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml constraints.txt | cksum | cut -d' ' -f1)
SLURM_STAMP := $(VENV)/.slurm-$(shell cat pyproject.toml constraints.txt | cksum | cut -d' ' -f1)
CORES ?= 2

.PHONY: install install-slurm run paper test test-cluster lint clean

# The compiled cores (the pose solver's, the markers', the CSV float cells') are rebuilt when their sources change.
$(STAMP): pyproject.toml constraints.txt setup.py dmais_pipe/pose/_kernels.pyx dmais_pipe/pose/_refine.pyx \
		dmais_pipe/pose/_group.pyx dmais_pipe/pose/_error.pyx dmais_pipe/pose/_certificate.pyx dmais_pipe/pose/_small.pxd \
		dmais_pipe/markers/_xfit.pyx dmais_pipe/markers/_rings.pyx dmais_pipe/markers/_centring.pyx dmais_pipe/markers/_sums.pxd \
		dmais_pipe/markers/_rings.pxd dmais_pipe/markers/_shadow.pyx dmais_pipe/_float_text.pyx
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	PIP_CONSTRAINT=$(abspath constraints.txt) $(BIN)/python -m pip install --quiet -e '.[test]'
	rm -f $(VENV)/.installed-* && touch $@

install: $(STAMP)

# Snakemake's SLURM executor plugin (README, "Running on a cluster").
$(SLURM_STAMP): $(STAMP)
	PIP_CONSTRAINT=$(abspath constraints.txt) $(BIN)/python -m pip install --quiet -e '.[slurm]'
	rm -f $(VENV)/.slurm-* && touch $@

install-slurm: $(SLURM_STAMP)

run: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/config.yaml

paper: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/paper.yaml

test: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/python -m pytest -q

# The demo and a campaign slice through the SLURM profile on a SLURM of three nodes brought up here (as
# root, from Debian's packages: tests/cluster/slurm_up.sh), one node killed midway; tables compared with
# local runs'.
test-cluster: $(SLURM_STAMP)
	PATH="$(BIN):$$PATH" DMAIS_CLUSTER_TEST=1 $(BIN)/python -m pytest -q tests/cluster

lint: $(STAMP)
	PATH="$(BIN):$$PATH" $(BIN)/snakemake --lint --configfile config/config.yaml

clean:
	rm -rf results logs .snakemake data
