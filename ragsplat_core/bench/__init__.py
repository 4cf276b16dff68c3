"""Measuring tools kept apart from the core: the refraction stability sweep, the solver, rasterizer and
training-step benchmarks, and the small synthetic scenes they and the tests render. The `ragsplat
stability` and `ragsplat bench` commands (in `ragsplat.cli`) print and save what these return."""

import os


def openmp_wait() -> dict[str, str]:
    """How this process's OpenMP threads wait (the CLI sets it before torch loads; it moves CPU timings a
    lot), for a benchmark's record: {"omp_wait_policy", "gomp_spincount"}, "" where unset."""
    return {"omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", ""),
            "gomp_spincount": os.environ.get("GOMP_SPINCOUNT", "")}
