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

No wait on a cluster is unbounded: connecting gives up after ``timeout`` seconds, and
``run_tasks`` raises ``ClusterError`` when the scheduler has had no worker that can take a
task (none, or all paused) for ``NO_WORKER_S`` seconds, or goes away (the results that came back are kept).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time

from massspring.support.extras import install_hint

EXTRA = install_hint("cluster")
SCHEMES = ("tcp://",)  # what --address accepts (besides HOST:PORT, which is tcp)
NO_WORKER_S = 60.0  # seconds a scheduler may go without a worker that takes tasks while tasks wait
POLL_S = 2.0  # seconds between checks of the scheduler while waiting for results


class ClusterError(RuntimeError):
    """The cluster cannot finish the tasks: no workers, or the scheduler went away."""

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
    if isinstance(address, str) and "://" in address and not address.startswith(SCHEMES):
        raise ValueError(f"--address: {address.split('://')[0]}:// is not supported (TLS and UCX need settings "
                         f"this command does not take); give a tcp://HOST:PORT address")
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
        except (OSError, ValueError, TypeError) as exc:  # refused, timed out, or an address Dask cannot parse
            raise ValueError(f"--address: no Dask scheduler answers at {address} within {timeout} s "
                             f"({type(exc).__name__}: {exc})") from None
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
    pending, stalled_since = set(futures), None
    try:
        while pending:
            try:
                done = distributed.wait(pending, timeout=POLL_S, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = ()
            except distributed.client.FuturesCancelledError:
                raise ClusterError(f"the Dask scheduler went away with {len(pending)} task(s) unfinished") from None
            for future in done:
                pending.discard(future)
                index = futures[future]
                try:
                    results[index] = future.result()
                except distributed.KilledWorker as exc:  # its worker died more often than Dask retries
                    if not keep_lost:
                        raise
                    results[index] = exc
                except distributed.client.FutureCancelledError:
                    raise ClusterError(f"the Dask scheduler went away with {len(pending) + 1} task(s) "
                                       "unfinished") from None
                if on_result:
                    on_result(index, results[index])
            if pending and not done:
                stalled_since = _check_workers(client, stalled_since, len(pending))
    finally:
        with contextlib.suppress(Exception):  # a scheduler that is gone has nothing to cancel
            client.cancel(list(futures))
    return results


def _check_workers(client, stalled_since, waiting):
    """While ``waiting`` tasks wait: the time since which no worker can take them (None while
    one can): the scheduler has no worker, or every worker is paused (Dask pauses a worker
    whose memory passes its pause fraction) and none is still executing a task.
    ClusterError after ``NO_WORKER_S`` seconds of that, or when the scheduler does not answer."""
    try:
        workers = client.scheduler_info(n_workers=-1).get("workers", {})
    except Exception as exc:
        raise ClusterError(f"the Dask scheduler does not answer ({type(exc).__name__}: {exc}); "
                           f"{waiting} task(s) unfinished") from None
    if any(_can_work(worker) for worker in workers.values()):
        return None
    now = time.monotonic()
    if stalled_since is None:
        return now
    if now - stalled_since <= NO_WORKER_S:
        return stalled_since
    if workers:
        raise ClusterError(f"every worker of the Dask scheduler ({len(workers)}) has been paused for "
                           f"{NO_WORKER_S:g} s ({waiting} task(s) unfinished): Dask pauses a worker whose memory "
                           "passes its pause fraction; give the workers more memory (dask worker --memory-limit) "
                           "and run the same command again")
    raise ClusterError(f"the Dask scheduler has had no worker for {NO_WORKER_S:g} s ({waiting} task(s) "
                       "unfinished): start workers (dask worker ADDRESS) and run the same command again")


def _can_work(worker):
    """Whether a worker (an entry of ``scheduler_info``'s workers) takes tasks or is running one."""
    if worker.get("status", "running") == "running":
        return True
    counts = worker.get("metrics", {}).get("task_counts", {})
    return counts.get("executing", 0) + counts.get("long-running", 0) > 0
