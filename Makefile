# One-command install and the project's jobs. Everything runs inside .venv.
PYTHON_SYS ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
# OpenMP threads spin briefly before sleeping: long spins slow jobs that share the cores, none slows every
# small tensor op (measured; see ragsplat_core/cli/main.py). Only without the user's own OMP_WAIT_POLICY:
# libgomp lets GOMP_SPINCOUNT override it (measured), and the user's setting must win.
ifndef OMP_WAIT_POLICY
export GOMP_SPINCOUNT ?= 2000
endif
PRESET ?= small
# The training preset of a dataset preset: small-bed -> small, paper-reach -> paper.
TRAIN_PRESET ?= $(firstword $(subst -, ,$(PRESET)))
SEED ?= 0
# Training seeds of the ablation (tables: mean +- std over them) and its variants (empty: all).
SEEDS ?= 0 1 2
VARIANTS ?=
# How every variant starts: refracted (tracks triangulated from the images, rays bent at the water: nothing
# about the bed given), triangulated (straight rays, depths x n) or grid (the paper's plane at the bed depth,
# which a reach with pools and banks has no single value of)
INIT ?= refracted
# Rows trained at once, each process with cores / JOBS threads (2 single-threaded on 2 cores: 1.7x the steps)
JOBS ?= 2
DATA ?= data/$(PRESET)
RUNS ?= runs/$(PRESET)

.PHONY: install test lint dataset ablation clean

install: $(VENV)/.installed

# Re-runs only when the dependency list changes.
$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON_SYS) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# Pinned first: it takes the local CPU build; an unpinned torch pulls gigabytes of CUDA packages.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $@

test: install
	$(PY) -m pytest -q

# Renders the synthetic riverbed (resumes: finished views are skipped).
dataset: install
	$(VENV)/bin/ragsplat dataset --preset $(PRESET) --out $(DATA) --seed $(SEED) $(if $(SHARD),--shard $(SHARD))

# The main job: dataset if missing, every variant trained and evaluated, tables beside the paper's.
ablation: dataset
	$(VENV)/bin/ragsplat ablation --preset $(TRAIN_PRESET) --data $(DATA) --out $(RUNS) --seeds $(SEEDS) --init $(INIT) --jobs $(JOBS) $(if $(VARIANTS),--variants $(VARIANTS))

lint: install
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache
