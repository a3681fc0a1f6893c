"""Where many independent runs go: a Dask cluster, or this process.

A sweep, a study or a stability ladder is a list of independent tasks, each a plain
function of plain (picklable) arguments. ``run_tasks`` hands them to a
``dask.distributed.Client`` (one Dask task per run; Dask reschedules a task whose
worker dies) or, without a client, calls them here one after another. A worker
process keeps its Taichi runtime and its pool of fields between tasks
(``massspring.device``), so each kernel compiles once per worker and size class.

``cluster(workers, address)`` opens the client of the command line's ``--workers N``
(a local cluster of N worker processes, shut down afterwards; each runs one task at a
time, its Taichi loops on its share of the CPUs, ``TI_CPU_MAX_NUM_THREADS`` = CPUs // N
unless that variable is set) or
``--address tcp://HOST:PORT`` (a running ``dask scheduler``), or None for neither.
Dask is the optional extra ``cluster`` (``extras.install_hint``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading

from massspring.extras import install_hint

EXTRA = install_hint("cluster")

# One Taichi runtime per process: tasks on a worker with several threads take turns.
_TAICHI = threading.Lock()


def exclusive(function, *args, **kwargs):
    """``function(*args, **kwargs)`` while holding this process's Taichi lock (the
    wrapper every task runs in, here or on a worker)."""
    with _TAICHI:
        return function(*args, **kwargs)


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ValueError(f"--workers/--address: Dask is not installed ({EXTRA})") from None
    return distributed


def check_options(workers=None, address=None):
    """Refuse bad ``--workers`` / ``--address`` values (ValueError naming the option)
    before any run; Dask must be installed for either."""
    if workers is not None and address is not None:
        raise ValueError("--workers/--address: give one of them (a local cluster, or a running scheduler)")
    if workers is not None and not (isinstance(workers, int) and 1 <= workers <= 1024):
        raise ValueError(f"--workers: expected a number of worker processes in 1..1024, got {workers!r}")
    if address is not None and (not isinstance(address, str) or "://" not in address and ":" not in address):
        raise ValueError(f"--address: expected a scheduler address such as tcp://HOST:8786, got {address!r}")
    if workers is not None or address is not None:
        _distributed()


@contextlib.contextmanager
def cluster(workers=None, address=None, timeout=10):
    """A ``distributed.Client`` for ``workers`` local processes or the scheduler at
    ``address`` (closed, and the local cluster shut down, when the block ends), or None
    when both are None (run in this process)."""
    check_options(workers, address)
    if workers is None and address is None:
        yield None
        return
    distributed = _distributed()
    if address is not None:
        try:
            client = distributed.Client(address, timeout=timeout)
        except OSError as exc:
            raise ValueError(f"--address: no Dask scheduler answers at {address} ({exc})") from None
        with client:
            yield client
        return
    threads = os.environ.get("TI_CPU_MAX_NUM_THREADS") or str(max(1, (os.cpu_count() or 1) // workers))
    local = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                     dashboard_address=":0", silence_logs=logging.ERROR,
                                     env={"TI_CPU_MAX_NUM_THREADS": threads})
    with local, distributed.Client(local) as client:
        yield client


def run_tasks(function, tasks, client=None, on_result=None, keep_lost=False):
    """``[function(*task) for task in tasks]``, on ``client``'s workers when given.

    ``on_result(index, result)`` is called as each task finishes (in finishing order on a
    cluster, in order here). A task whose worker dies is rerun by Dask (up to its
    ``allowed-failures``); if it still cannot finish, ``distributed.KilledWorker`` is
    raised here, or with ``keep_lost`` becomes that task's result (a sweep's failed row).
    An exception the function raises is raised here, as in this process. Returns the
    results in the tasks' order."""
    tasks = list(tasks)
    results = [None] * len(tasks)
    if client is None:
        for index, task in enumerate(tasks):
            results[index] = exclusive(function, *task)
            if on_result:
                on_result(index, results[index])
        return results
    distributed = _distributed()
    futures = {client.submit(exclusive, function, *task, pure=False): index for index, task in enumerate(tasks)}
    try:
        for future in distributed.as_completed(futures):
            index = futures[future]
            try:
                results[index] = future.result()
            except distributed.KilledWorker as exc:  # its worker died more often than Dask retries
                if not keep_lost:
                    raise
                results[index] = exc
            if on_result:
                on_result(index, results[index])
    finally:
        client.cancel(list(futures))
    return results
