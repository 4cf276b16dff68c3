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
# The training preset of a dataset preset: small-bed -> small, paper-reach -> paper, smoke-long -> smoke;
# small-field and long have their own; the mapping flights' photos of a few cm a pixel train with long's.
TRAIN_PRESET ?= $(if $(filter small-field,$(PRESET)),small-field,$(if $(filter lake-mapping river-mapping,\
	$(PRESET)),long,$(firstword $(subst -, ,$(PRESET)))))
SEED ?= 0
# The ablation's training seeds (e.g. SEEDS="0 1"), variants (VARIANTS="3dgs full"), start (INIT=grid |
# triangulated | refracted), processes (JOBS=1) and training device (DEVICE=cuda | cpu): empty means
# `ragsplat ablation`'s own defaults, defined once in the library (the start in ragsplat_core/train/config.py,
# the variants and jobs in train/defaults.py, the seeds in eval/ablation.py; `ragsplat ablation --help` prints
# them).
SEEDS ?=
VARIANTS ?=
INIT ?=
JOBS ?=
DEVICE ?=
# ONE_LEVEL=1: the method and the references given one flat water level, the mean of the dataset's surveyed
# edge points, instead of its (sloping) surface (`ragsplat ablation --one-level`; use another RUNS).
ONE_LEVEL ?=
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

# One worker process a core, at most four (a Blender render or a training each), a test file to one worker so
# that its fixtures are made once.
test: install
	$(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile

# Renders the synthetic riverbed (resumes: finished views are skipped).
dataset: install
	$(VENV)/bin/ragsplat generate --preset $(PRESET) --out $(DATA) --seed $(SEED) $(if $(SHARD),--shard $(SHARD))

# The main job: dataset if missing, every variant trained and evaluated, tables beside the paper's.
ablation: dataset
	$(VENV)/bin/ragsplat ablation --preset $(TRAIN_PRESET) --data $(DATA) --out $(RUNS)$(if $(SEEDS), --seeds $(SEEDS))$(if $(INIT), --init $(INIT))$(if $(JOBS), --jobs $(JOBS))$(if $(DEVICE), --device $(DEVICE))$(if $(VARIANTS), --variants $(VARIANTS))$(if $(ONE_LEVEL), --one-level)

lint: install
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache
