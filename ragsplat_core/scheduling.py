"""Tasks on a Dask client (`ragsplat ablation`'s rows, `ragsplat survey`'s tiles): submitted, then taken
one by one as each finishes, the unfinished cancelled when the caller stops."""

from __future__ import annotations

from collections.abc import Callable, Iterator

# While the tasks run, the caller's `check` (a deferred Ctrl-C raises there) runs at least this often (s).
CHECK_EVERY = 0.5


def submitted(client, calls: dict, check: Callable[[], None] | None = None) -> Iterator[tuple[str, object]]:
    """Submits each of `calls` ({key: (function, args)}; the key names the task) to `client` and yields
    (key, future) as each finishes, whether it finished, failed or was cancelled (`future.status`), calling
    `check()` while it waits. Whatever stops the caller (an exception, `check`'s, or the generator closed
    early) cancels the tasks not yet finished."""
    from dask.distributed import wait

    futures = {client.submit(fn, *args, key=str(key), pure=False): key for key, (fn, args) in calls.items()}
    pending = set(futures)
    try:
        while pending:
            if check is not None:
                check()
            try:
                wait(list(pending), timeout=CHECK_EVERY, return_when="FIRST_COMPLETED")
            except TimeoutError:
                continue
            for future in [f for f in pending if f.done()]:
                pending.discard(future)
                yield futures[future], future
    finally:
        if pending:
            client.cancel(list(pending))
