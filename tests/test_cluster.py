"""The local Dask cluster the commands start (`cli.cluster.client`): its workers get the thread counts and
the quieter periodic callbacks, in the worker processes themselves (set in the parent, passed on by the
nannies)."""

import os

from ragsplat.cli.cluster import QUIET_WORKERS, client
from ragsplat.threads import THREAD_VARIABLES, cores_share


def _worker_settings(names):
    import dask

    return {name: dask.config.get(name) for name in names}, {v: os.environ.get(v) for v in THREAD_VARIABLES}


def test_local_workers_run_with_the_thread_counts_and_the_quiet_callbacks():
    before = dict(os.environ)
    with client(2) as (c, where):
        assert dict(os.environ) == before  # the nannies' settings are the workers', not this process's
        seen = c.run(_worker_settings, list(QUIET_WORKERS))
    assert dict(os.environ) == before
    assert where.startswith("2 local Dask workers")
    assert len(seen) == 2
    threads = str(max(1, (os.cpu_count() or 1) // 2))
    for config, env in seen.values():
        assert config == QUIET_WORKERS
        assert env == {v: threads for v in THREAD_VARIABLES}


def test_processes_sharing_the_cores_get_one_thread_at_least():
    cores = os.cpu_count() or 1
    assert cores_share(1) == str(cores)
    assert cores_share(2) == str(max(1, cores // 2))
    assert cores_share(4 * cores) == "1"
