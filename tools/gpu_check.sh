#!/usr/bin/env bash
# The GPU figures of docs/lab/performance.md ("On a GPU"), in stages that end inside 10 minutes on one H100
# (a lent machine's limit for one command); what they print also goes to OUT/STAGE.log.
#   bash tools/gpu_check.sh tests OUT         the CUDA and gsplat tests, then `ragsplat bench train-step`
#                                             with the compiled transform (OUT/train_step.json)
#   bash tools/gpu_check.sh ablation OUT DATA `ragsplat ablation` on DATA (the dataset or its slim copy,
#                                             `python -m tools.slim`), its small files in OUT/rows.tar.gz
#   bash tools/gpu_check.sh all OUT DATA      both in one command (one machine start, one gsplat compile):
#                                             the ablation gets what is left of LIMIT_S after the tests
# Needs a CUDA torch, gsplat and ragsplat itself installed where PYTHON runs: ragsplat from its wheel, built
# here into .gpu/whl (`.venv/bin/pip wheel --no-deps --no-build-isolation -w .gpu/whl .`) and installed there
# with the other wheels (docs/lab/performance.md, "The GPU checks in one command"); the checkout gives the tests
# and the commands run from the installed package. Settings (environment): PYTHON (python3), DEVICE (cuda),
# BACKENDS (gsplat:cuda), PRESET (small), VARIANTS ("full 2dgs+full"), SEEDS ("0 1 2"), RUNS (OUT/runs:
# the ablation's folder; elsewhere, a rerun on the same machine resumes), LIMIT_S (540 s: the ablation, or
# with `all` the whole stage, is stopped then and its finished rows packed). The same stages run on a CPU
# with DEVICE=cpu BACKENDS=cpu:cpu PRESET=smoke (the plumbing only: the tests of CUDA skip there).
set -euo pipefail
stage=${1:?stage: tests, ablation or all} out=${2:?OUT folder}
root="$(cd "$(dirname "$0")/.." && pwd)"
if [ "$stage" = all ]; then
    data=${3:?DATA: the dataset or its slim copy}
    # a failed test does not cancel the ablation (its rows are the other half of the figures); the
    # stage's exit is the first failure's
    rc=0
    bash "$0" tests "$out" || rc=$?
    left=$(( ${LIMIT_S:-540} - SECONDS ))
    if [ "$left" -lt 60 ]; then  # (and `timeout 0` would be no limit at all)
        echo "all: ${left} s of LIMIT_S left after the tests; the ablation is not started" >&2
        exit $(( rc ? rc : 124 ))
    fi
    rc_ablation=0
    LIMIT_S=$left bash "$0" ablation "$out" "$data" || rc_ablation=$?
    exit $(( rc ? rc : rc_ablation ))
fi
py=${PYTHON:-python3}
mkdir -p "$out"
out="$(cd "$out" && pwd)"
exec > >(tee "$out/$stage.log") 2>&1
cd "$root"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null \
    || echo "no nvidia-smi"
"$py" -c 'import sys, numpy, torch, ragsplat
print(sys.version.split()[0], "torch", torch.__version__, "numpy", numpy.__version__,
      "cuda", torch.cuda.is_available(), "ragsplat from", ragsplat.__path__[0])'
# the installed ragsplat must be this checkout's sources (a wheel in .gpu/whl built before the last edit
# would measure other code): every .py of the four folders, byte for byte, where the wheel puts it
"$py" -c 'import importlib.util, sys
from pathlib import Path
from ragsplat.outputs import SOURCE_PACKAGES
root, stale = Path(sys.argv[1]), []
for folder, package in SOURCE_PACKAGES.items():
    where = Path(importlib.util.find_spec(package).submodule_search_locations[0])
    for path in sorted((root / folder).rglob("*.py")):
        rel = path.relative_to(root / folder)
        if "__pycache__" not in rel.parts and not ((where / rel).is_file()
                                                   and (where / rel).read_bytes() == path.read_bytes()):
            stale.append(f"{folder}/{rel}")
if stale:
    sys.exit(f"the installed ragsplat is not this checkout: {stale[0]} and {len(stale) - 1} more differ; "
             "rebuild .gpu/whl")' "$root"
case "$stage" in
tests)
    SECONDS=0
    rc=0
    # a failed test does not cancel the bench (one try on a lent GPU); the stage exits with its code
    "$py" -m pytest -q -p no:cacheprovider tests/test_surfel.py tests/test_rasterize_backends.py \
        tests/test_refraction.py || rc=$?
    echo "tests: ${SECONDS} s (gsplat's first use compiles it), exit ${rc}"
    # shellcheck disable=SC2086 (a list)
    "$py" -m ragsplat.cli.main bench train-step --backends ${BACKENDS:-gsplat:cuda} \
        --counts 40000 200000 --compile --out "$out/train_step.json"
    exit "$rc"
    ;;
ablation)
    data=${3:?DATA: the dataset or its slim copy}
    runs=${RUNS:-$out/runs}
    SECONDS=0
    rc=0
    # stopped (SIGTERM: checkpoints written) before the caller's limit, so the finished rows come back
    # shellcheck disable=SC2086 (lists)
    timeout "${LIMIT_S:-540}" "$py" -m ragsplat.cli.main ablation --preset "${PRESET:-small}" \
        --data "$data" --out "$runs" --device "${DEVICE:-cuda}" --variants ${VARIANTS:-full 2dgs+full} \
        --seeds ${SEEDS:-0 1 2} --no-download --no-geotiffs || rc=$?
    echo "ablation: ${SECONDS} s wall, exit ${rc}"
    (cd "$runs" && find . \( -name row.json -o -name '*.md' -o -name results.json -o -name '*.log' \
        -o -name error_vs_time.png \) -print0 | tar czf "$out/rows.tar.gz" --null -T -)
    exit "$rc"
    ;;
*)
    echo "unknown stage $stage (tests, ablation or all)" >&2
    exit 2
    ;;
esac
