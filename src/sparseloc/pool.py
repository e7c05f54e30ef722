"""Execution in worker processes: how many cores a run may use, and a pool that solves items
(frames) in its processes and yields their results in order.

The chunked runs of :mod:`sparseloc.distributed` (threads or a Dask cluster) are the other
execution strategy; one process is the pipeline's own loop.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from .engine import set_engine

__all__ = ["available_cores", "in_processes"]


def _cpu_quota(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """CPUs allowed by a Linux cgroup quota (a container's ``--cpus``, a batch job's limit),
    or None where there is none or it cannot be read. The core affinity does not show it: a
    container limited to 2 CPUs on a 64-core host sees 64 cores."""
    try:
        if (root / "cpu.max").exists():  # cgroup v2: "QUOTA PERIOD" or "max PERIOD"
            quota, period = (root / "cpu.max").read_text().split()[:2]
            return None if quota == "max" else int(quota) / int(period)
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())  # cgroup v1
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 or period <= 0 else quota / period
    except (OSError, ValueError):
        return None


def available_cores() -> int:
    """CPU cores this process may use: its affinity (else the CPU count), lowered by a
    cgroup CPU quota; at least 1. The default worker counts (``localize`` on the command
    line, ``sparseloc demo``) start from it."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        cores = os.cpu_count() or 1
    quota = _cpu_quota()
    if quota is not None:
        cores = min(cores, int(quota))
    return max(1, cores)


_WORK: Any = None  # this worker process's solver (see _init_worker)


#: Seconds between a worker's checks that its parent still lives.
PARENT_CHECK_SECONDS = 0.5


def _watch_parent(parent: int) -> None:
    """End this worker process as soon as its parent is gone (killed with SIGKILL, the pool
    never shut down): an orphaned worker would otherwise finish its items and then wait for
    work forever, holding its memory. Runs in a daemon thread of the worker."""
    import time

    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_SECONDS)
    os._exit(1)


def _init_worker(
    make_work: Callable[..., Any], args: tuple, engine: str, parent: int | None = None
) -> None:
    global _WORK
    import signal
    import threading

    # Ctrl-C reaches the whole process group: the parent alone answers it (it ends the pool);
    # a worker interrupted mid-item would leave the pool broken and its shutdown waiting.
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    # ``parent``: the pool's process id, given so that a parent dead before this line is seen
    threading.Thread(
        target=_watch_parent,
        args=(os.getppid() if parent is None else parent,),
        name="sparseloc-parent-watch",
        daemon=True,
    ).start()
    # One BLAS thread per process: the processes already share out the cores.
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    set_engine(engine)
    _WORK = make_work(*args)


def _solve_in_worker(*item: Any) -> Any:
    assert _WORK is not None
    return _WORK(*item)


def in_processes(
    items: Iterable[tuple], workers: int, init: tuple[Callable[..., Any], tuple, str]
) -> Iterator[Any]:
    """Solve ``items`` in a pool of ``workers`` processes; yield the results in order.

    ``init = (make_work, args, engine)``: each process builds its solver once as
    ``make_work(*args)`` (with the engine setting ``engine``) and calls it as ``work(*item)``.
    At most ``4 * workers`` items are in flight, so memory stays bounded on long movies.
    """
    import multiprocessing
    from collections import deque
    from concurrent.futures import ProcessPoolExecutor

    # The platform's default: fork on Linux (no re-import of the caller's script), spawn
    # elsewhere (scripts then need the usual ``if __name__ == "__main__":`` guard).
    ctx = multiprocessing.get_context()
    pool = ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_init_worker, initargs=(*init, os.getpid())
    )
    try:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(_solve_in_worker, *item))
            if len(pending) >= 4 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    except BaseException:
        # Interrupted (Ctrl-C, an error, the caller stopped reading): the items in flight are
        # dropped and the workers ended now, not waited for; a second Ctrl-C finds nothing
        # left to hang on.
        _end_now(pool)
        raise
    pool.shutdown(wait=True)


def _end_now(pool) -> None:
    """Cancel a process pool's queued items and terminate its workers."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        proc.terminate()
    for proc in procs:
        proc.join(timeout=5)
