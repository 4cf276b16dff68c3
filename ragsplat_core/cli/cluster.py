"""The Dask client the commands schedule their tasks on (`ragsplat ablation`'s rows, `ragsplat survey`'s
tiles): a local cluster of worker processes on this machine, or an existing cluster's scheduler."""

from __future__ import annotations

import contextlib
import logging
import os


@contextlib.contextmanager
def client(jobs: int, scheduler: str | None = None):
    """Yields (a `dask.distributed.Client`, where it runs in words): on the cluster at `scheduler`
    (tcp://host:8786), or on `jobs` local worker processes of one task each with cores / jobs threads."""
    import dask
    from dask.distributed import Client, LocalCluster

    from ragsplat.threads import THREAD_VARIABLES

    if scheduler:
        with Client(scheduler) as c:
            yield c, f"the Dask cluster at {scheduler}"
        return
    threads = str(max(1, (os.cpu_count() or 1) // jobs))
    # the workers' environment from their start, instead of Dask's default, whose MALLOC_TRIM_THRESHOLD_ of
    # 64 KiB (memory handed back to the system at once) made a smoke ablation's rows spend a third of their
    # time in the kernel: 1.63x the wall time of the same rows without Dask
    with dask.config.set({"distributed.nanny.pre-spawn-environ": {
            name: threads for name in THREAD_VARIABLES}}), \
            LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None,
                         silence_logs=logging.CRITICAL) as cluster, Client(cluster) as c:
        yield c, f"{jobs} local Dask workers of {threads} thread(s)"
