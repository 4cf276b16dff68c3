"""How a process's OpenMP threads wait, set before torch loads (no torch here): the `ragsplat` command and
the maintainers' tools, which run several at once on shared cores, both call it first."""

import os

# What each threading library reads for its thread count at its start: a worker process that shares the cores
# sets them all (`cli.cluster`), or numba alone spins one thread per core beside the others' (two one-thread
# trainings ran 7x slower so, docs/performance.md).
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def cores_share(processes: int) -> str:
    """Each thread count of `THREAD_VARIABLES` for one of `processes` processes that share this machine's
    cores (at least one)."""
    return str(max(1, (os.cpu_count() or 1) // processes))


def openmp_waits() -> None:
    """How OpenMP threads (torch's and numba's, one libgomp) wait between parallel regions; it only takes
    effect if called before torch is imported, and the user's own setting wins. Spinning long (libgomp's
    default) made jobs that share the cores 2-80x slower; sleeping at once (OMP_WAIT_POLICY=PASSIVE) makes
    every small tensor op wait for its threads to wake: a 2-thread `full` step at 40k Gaussians took 0.107 s
    so, 0.071 s with a spin of 2 000 iterations, which costs jobs sharing the cores 1.1-1.3x (`ragsplat bench
    train-step`, measured)."""
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ.setdefault("GOMP_SPINCOUNT", "2000")
