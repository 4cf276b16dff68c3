"""The Dask client the commands schedule their tasks on (`ragsplat ablation`'s rows, `ragsplat survey`'s
tiles): a local cluster of worker processes on this machine, or an existing cluster's scheduler."""

from __future__ import annotations

import contextlib
import logging
import os

# A local worker's own threads wake less often than Dask's defaults, which take the GIL from the task many
# times a second (the event loop's tick, the statistical profiler for a dashboard we do not start, the
# process's memory and CPU read): with them the rows ran measurably slower than in plain processes
# (docs/lab/performance.md, "Quieter workers"). The workers' environment is set from their start
# (`pre-spawn-environ` below) instead of Dask's default, whose small MALLOC_TRIM_THRESHOLD_ (memory handed
# back to the system at once) made the rows spend much of their time in the kernel.
QUIET_WORKERS = {
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "10s",
    "distributed.worker.memory.monitor-interval": "1s",
}


@contextlib.contextmanager
def client(jobs: int, scheduler: str | None = None):
    """Yields (a `dask.distributed.Client`, where it runs in words): on the cluster at `scheduler`
    (tcp://host:8786), or on `jobs` local worker processes of one task each with cores / jobs threads."""
    import dask
    from dask.distributed import Client, LocalCluster

    from ragsplat.threads import THREAD_VARIABLES, cores_share

    if scheduler:
        with Client(scheduler) as c:
            yield c, f"the Dask cluster at {scheduler}"
        return
    threads = cores_share(jobs)
    saved = dict(os.environ)
    try:
        with dask.config.set({**QUIET_WORKERS, "distributed.nanny.pre-spawn-environ": {
                name: threads for name in THREAD_VARIABLES}}), \
                LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None,
                             silence_logs=logging.CRITICAL) as cluster, Client(cluster) as c:
            _restore(saved)
            yield c, f"{jobs} local Dask workers of {threads} thread(s)"
    finally:
        _restore(saved)


def _restore(saved: dict) -> None:
    """This process's environment back to `saved`. A local cluster's nannies run in this process and set their
    `pre-spawn-environ` in its environment before each worker starts, and leave it there: the command's own
    numba, whose threads started under one NUMBA_NUM_THREADS, then refused to compile under another."""
    for name in set(os.environ) - set(saved):
        del os.environ[name]
    for name, value in saved.items():
        if os.environ.get(name) != value:
            os.environ[name] = value
