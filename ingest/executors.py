"""Executors for ingest tasks: in-process, a local process pool, or Ray. Same task function, same bytes.

A task is one subject (:class:`~relightanyone.ingest.runner.SubjectTask`); it writes its own part of the
:class:`~relightanyone.format.shards.ShardWriter` and returns a small
:class:`~relightanyone.ingest.runner.TaskResult`, so the coordinator never holds pixels and its memory
does not grow with the number of subjects. The commit that follows sorts rows by key, which makes the
dataset independent of the order in which tasks finish. Before the tasks, the coordinator relates each
subject's frames to the tracking on the same executor (:func:`map_items`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from functools import partial

from relightanyone.errors import DependencyError
from relightanyone.ingest.subject_task import run_subject_task

EXECUTORS = ("local", "ray")
WORKER_PRELOAD = (
    "relightanyone.ingest.runner",  # the alignment's task function lives there
    "relightanyone.ingest.subject_task",
    "relightanyone.ingest.decode",
    "relightanyone.ingest.steps",
    "relightanyone.ingest.tracking",
    "relightanyone.align.colour",
    "relightanyone.align.geometry",
    "relightanyone.format.codecs",
    "relightanyone.format.shards",
    "cv2",
    "trimesh",
    "torch",  # calibration readers return tensors; importing it in every worker costs seconds
    "relightanyone.ingest.calibration",  # the tracker's cameras (imports kornia: 0.3 s per worker)
)


def _bar(total: int, progress: bool, desc: str):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="view")


def map_items(
    function: Callable,
    items: Sequence,
    workers: int = 1,
    executor: str = "local",
    on_done: Callable | None = None,
    cost: Callable | None = None,
) -> list:
    """``[function(item) for item in items]`` on an executor; results in item order.

    ``executor="local"``: in this process when ``workers == 1`` or there is one item, else a
    ``ProcessPoolExecutor`` of ``workers`` processes started by a ``forkserver`` (fresh interpreters, like
    ``spawn``: the function and items are pickled, nothing is inherited from the caller; the server imports
    the heavy modules once and every worker forks from it). ``executor="ray"``: ``ray.init(num_cpus=workers)``
    when Ray is not yet initialised (a running cluster is used as it is). ``on_done(item)`` runs in this
    process as each item finishes; ``cost(item)`` orders submission, largest first, so a long item does not
    start last and leave the other workers idle.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; expected one of {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    order = list(range(len(items)))
    if cost is not None:
        order.sort(key=lambda i: -cost(items[i]))
    if executor == "ray":
        results = _map_ray(function, items, order, workers, on_done)
    elif workers == 1 or len(items) <= 1:
        results = {}
        for i in order:
            results[i] = function(items[i])
            if on_done is not None:
                on_done(items[i])
    else:
        results = _map_pool(function, items, order, workers, on_done)
    return [results[i] for i in range(len(items))]


def run_tasks(
    writer, settings, tasks: Sequence, workers: int = 1, executor: str = "local", progress: bool = True
):
    """Run ``run_subject_task(writer, settings, task)`` for every task (:func:`map_items`); returns the
    results in task order. The progress bar counts views."""

    bar = _bar(sum(len(t.plan.views) for t in tasks), progress, f"ingest {settings.dataset}")
    try:
        return map_items(
            partial(run_subject_task, writer, settings),
            tasks,
            workers,
            executor,
            on_done=None if bar is None else lambda task: bar.update(len(task.plan.views)),
            cost=lambda task: len(task.plan.views),
        )
    finally:
        if bar is not None:
            bar.close()


# workers -> (owning pid, process pool) kept for this process's later calls; a forked child sees its
# parent's entries but not the threads that drive those pools, so it starts its own.
_POOLS: dict[int, tuple[int, object]] = {}
_POOLS_LOCK = threading.Lock()  # the warm-up thread and the caller may both ask for the pool first


def _local_pool(workers: int):
    """The process pool of ``workers`` workers, started on first use and kept until the process exits,
    so the alignment and the tasks of an ingest (and the next ingest) reuse warm workers. A pool whose
    worker died is replaced."""
    import atexit
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    with _POOLS_LOCK:
        owner, pool = _POOLS.get(workers, (None, None))
        if owner == os.getpid():
            if not getattr(pool, "_broken", False):
                return pool
            pool.shutdown(wait=False, cancel_futures=True)
        context = multiprocessing.get_context("forkserver")
        # Workers fork from a clean server process that imported the heavy modules once, instead of each
        # spawned worker importing them again; nothing is inherited from this (possibly threaded) process.
        context.set_forkserver_preload(list(WORKER_PRELOAD))
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=context)
        if not any(pid == os.getpid() for pid, _ in _POOLS.values()):
            atexit.register(shutdown_pools)
        _POOLS[workers] = (os.getpid(), pool)
        return pool


def _ready() -> bool:
    return True


def warm_local_pool(workers: int) -> threading.Thread | None:
    """Start the kept pool of ``workers`` processes in a background thread and return at once.

    The pool's server imports the heavy modules (about 4 s on two cores) before it forks a worker; a
    command that calls this first overlaps that with its own imports and planning, instead of paying it
    when its first task is submitted (without it, a cold 2-worker ingest of a small dataset was slower
    than a 1-worker one). Nothing to do for one worker, which runs in this process.
    """
    if workers < 2:
        return None

    def start() -> None:
        try:
            pool = _local_pool(workers)
            for _ in range(workers):  # each submit forks one worker, up to ``workers``
                pool.submit(_ready)
        except Exception:  # a failed warm-up is retried, and reported, by the real submit
            pass

    thread = threading.Thread(target=start, name="ingest-pool-warm-up", daemon=True)
    thread.start()
    return thread


def shutdown_pools() -> None:
    """Stop this process's kept pools (they also stop when it exits)."""
    import os

    for workers, (owner, pool) in list(_POOLS.items()):
        del _POOLS[workers]
        if owner == os.getpid():
            pool.shutdown(wait=True, cancel_futures=True)


def _map_pool(function, items, order, workers, on_done) -> dict:
    from concurrent.futures import FIRST_COMPLETED, wait

    results = {}
    pool = _local_pool(workers)
    futures = {pool.submit(function, items[i]): i for i in order}
    pending = set(futures)
    try:
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                i = futures[future]
                results[i] = future.result()
                if on_done is not None:
                    on_done(items[i])
    finally:
        for future in pending:  # an error or Ctrl-C here: do not leave the kept pool busy
            future.cancel()
    return results


def _call(function, item):
    return function(item)


def _map_ray(function, items, order, workers, on_done) -> dict:
    try:
        import ray
    except ImportError:
        raise DependencyError("the ray executor needs Ray: pip install 'relightanyone[ray]'") from None

    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    remote = ray.remote(num_cpus=1)(_call)
    function_ref = ray.put(function)
    refs = {remote.remote(function_ref, items[i]): i for i in order}
    results = {}
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        for ref in done:
            i = refs[ref]
            results[i] = ray.get(ref)
            if on_done is not None:
                on_done(items[i])
    return results
