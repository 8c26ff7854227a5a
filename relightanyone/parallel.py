"""Running one task function over many items: in this process, in a local process pool, or on Ray.

An :class:`Executor` maps a picklable function over items and returns the results in item order, whatever
the order in which they finish, so a task that writes its own output (a ``ShardWriter`` part) and returns
a small report gives the same bytes on every executor. Ingest (one task per subject) and the OLAT
expansion (one task per subject) both run on it.

* **In process**: ``kind="local"`` with one worker, or a single item.
* **Local pool**: ``kind="local"`` with ``workers > 1``: a ``ProcessPoolExecutor`` whose workers fork
  from a ``forkserver``, a clean process that imported the executor's ``preload`` modules once (fresh
  interpreters, like ``spawn``: the function and items are pickled, nothing is inherited from the
  caller). The pool is kept for the life of the calling process, so later maps reuse warm workers;
  :meth:`Executor.warm` starts it in a background thread while the caller is still planning. A pool that
  lost a worker is replaced; a forked child starts its own. Every pool is started by
  :func:`_start_pool`, the one place that sets what a worker does when it starts: it dies with the
  process that started the pool (see below).
* **Ray**: each item is a Ray task holding :class:`TaskResources` (CPUs, GPUs). With a cluster address
  (``address``, else ``RAY_ADDRESS``) the existing cluster is joined as it is; without one a local Ray
  of ``workers`` CPUs is started. A Ray already initialised in this process is used as it is.

No process of a pool outlives its caller, even one killed with SIGKILL, which runs no clean-up. Each pool
holds a *lifeline*, a pipe whose only write end stays in the caller (the forkserver and the resource
tracker are started with only the descriptors they need, so they hold no copy). Each worker starts by
asking the kernel to SIGKILL it when its parent, the forkserver, dies (:func:`die_with_parent`) and by
starting a thread that waits on the lifeline's read end: the caller never writes to it, so the read
returns only at end of file, when the caller is gone, and the thread then SIGKILLs the worker, whatever
task it is running. The forkserver and the resource tracker exit by themselves once every process that
holds their pipes, the workers included, has ended. A task never makes its own output count either:
a ``ShardWriter`` part written in a worker is published by the caller when the task's result arrives
(:meth:`relightanyone.format.shards.ShardWriter.publish`), so a worker that had not yet died could not
publish anything after its caller was killed. The forkserver gets no parent-death signal of its own:
the kernel ties that signal to the thread that forked, and the server is started by whichever thread
first needs it, often the short-lived warm-up thread. Ray's processes are Ray's to manage and are not
covered by any of this; a Ray task's part is still published only by the caller.

Tasks limit their own threads (:func:`cpu_share` is a worker's share of this machine's CPUs), so
``workers`` tasks side by side do not oversubscribe it.
"""

from __future__ import annotations

import atexit
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from relightanyone.errors import DependencyError, InputError

EXECUTORS = ("local", "ray")
PR_SET_PDEATHSIG = 1  # prctl(2) option: the signal this process gets when its parent dies
_local_ray_started = False  # this process has started a local Ray (it can no longer join a cluster)


@dataclass(frozen=True)
class TaskResources:
    """What one task holds on Ray. A local pool runs ``workers`` tasks at once whatever they ask for."""

    cpus: float = 1.0
    gpus: float = 0.0


@dataclass(frozen=True)
class Executor:
    """Where tasks run: ``kind`` "local" (this process or a kept process pool) or "ray".

    workers: tasks at once (the local pool's size; the CPUs of a local Ray). address: a Ray cluster to
    join (default ``RAY_ADDRESS``). preload: modules the local pool's server imports once; the server is
    started by the first pool of a process, so that pool's list is the one that counts.
    """

    kind: str = "local"
    workers: int = 1
    address: str | None = None
    preload: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in EXECUTORS:
            raise ValueError(f"unknown executor {self.kind!r}; expected one of {', '.join(EXECUTORS)}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")

    def in_process(self, items: int) -> bool:
        """Whether a map of ``items`` items runs in this process."""
        return self.kind == "local" and (self.workers == 1 or items <= 1)

    def cpu_share(self) -> int:
        """Threads each task may use: :func:`cpu_share` of this executor."""
        return cpu_share(self.workers, self.kind)

    def map(
        self,
        function: Callable,
        items: Sequence,
        on_done: Callable[[Any], None] | None = None,
        cost: Callable[[Any], Any] | None = None,
        resources: TaskResources = TaskResources(),
    ) -> list:
        """``[function(item) for item in items]`` on this executor; results in item order.

        ``on_done(item)`` runs in this process as each item finishes (progress bars count finished tasks).
        ``cost(item)`` orders submission, largest first (ties keep item order), so a long item does not
        start last and leave the other workers idle. ``resources`` is what each task holds on Ray.
        """
        order = list(range(len(items)))
        if cost is not None:
            order.sort(key=lambda i: cost(items[i]), reverse=True)
        if self.kind == "ray":
            results = _map_ray(function, items, order, on_done, self._ray(), resources)
        elif self.in_process(len(items)):
            results = {}
            for i in order:
                results[i] = function(items[i])
                if on_done is not None:
                    on_done(items[i])
        else:
            results = _map_pool(function, items, order, on_done, _local_pool(self.workers, self.preload))
        return [results[i] for i in range(len(items))]

    def warm(self) -> threading.Thread | None:
        """Start the kept local pool in a background thread and return at once (None when tasks will run
        in this process or on Ray).

        The pool's server imports the preload modules (seconds) before it forks a worker; a command that
        calls this first overlaps that with its own imports and planning instead of paying it when its
        first task is submitted.
        """
        if self.kind != "local" or self.workers < 2:
            return None

        def start() -> None:
            try:
                pool = _local_pool(self.workers, self.preload)
                for _ in range(self.workers):  # each submit forks one worker, up to ``workers``
                    pool.submit(_ready)
            except Exception:  # a failed warm-up is retried, and reported, by the real submit
                pass

        thread = threading.Thread(target=start, name="executor-pool-warm-up", daemon=True)
        thread.start()
        return thread

    def _ray(self):
        global _local_ray_started
        try:
            import ray
        except ImportError:
            raise DependencyError("the ray executor needs Ray: pip install 'relightanyone[ray]'") from None
        if not ray.is_initialized():
            arguments = ray_init_arguments(self.address, self.workers, os.environ)
            joins_cluster = "address" in arguments
            if joins_cluster and _local_ray_started:
                # Ray loses a cluster joined after a local Ray in the same process (its tasks then fail
                # with OwnerDiedError): refuse at once instead.
                raise InputError(
                    f"this Python process already started a local Ray, so it cannot join the cluster at "
                    f"{arguments['address']}: run the job from a new process (restart the interpreter)"
                )
            ray.init(**arguments)
            _local_ray_started = _local_ray_started or not joins_cluster
        return ray


def cpu_share(workers: int, kind: str = "local") -> int:
    """Threads for each of ``workers`` tasks running at once: this machine's CPUs shared out (at least 1);
    1 on Ray, whose tasks each hold one CPU wherever they run."""
    if kind == "ray":
        return 1
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cpus // max(1, workers))


def ray_init_arguments(address: str | None, workers: int, environ: Mapping[str, str]) -> dict:
    """``ray.init`` keyword arguments: join the cluster at ``address`` (else ``RAY_ADDRESS``) as it is, or
    start a local Ray of ``workers`` CPUs (a cluster refuses ``num_cpus``: its nodes declare their own)."""
    address = address or environ.get("RAY_ADDRESS") or None
    if address is not None:
        return {"address": address, "log_to_driver": False}
    return {"num_cpus": workers, "include_dashboard": False, "log_to_driver": False}


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux ``PR_SET_PDEATHSIG``; elsewhere
    nothing). Safe between fork and exec. The "parent" is the thread that forked this process, so a process
    forked from a short-lived thread must not call it."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # no libc prctl: the lifeline still ends the process
        pass


def _die_at_end_of_file(lifeline: Connection) -> None:
    """Block on ``lifeline`` until its write end closes (nothing is ever sent), then SIGKILL this process."""
    try:
        lifeline.recv_bytes()
    except (EOFError, OSError):
        pass
    os.kill(os.getpid(), signal.SIGKILL)


def _start_worker(lifeline: Connection) -> None:
    """What every pool worker runs first: die with the forkserver, and with the pool's caller when the
    ``lifeline`` reaches end of file (at once if the caller is already gone)."""
    die_with_parent()
    threading.Thread(
        target=_die_at_end_of_file, args=(lifeline,), name="executor-lifeline", daemon=True
    ).start()


@dataclass
class _Pool:
    """A kept pool: the process that started it, the pool, and the write end of its workers' lifeline."""

    owner: int
    pool: ProcessPoolExecutor
    lifeline: Connection

    def close(self, wait: bool) -> None:
        self.pool.shutdown(wait=wait, cancel_futures=True)
        self.lifeline.close()  # a worker still running (a broken pool's) dies now


# workers -> the pool kept for this process's later maps; a forked child sees its parent's entries but not
# the threads that drive those pools, so it starts its own.
_POOLS: dict[int, _Pool] = {}
_POOLS_LOCK = threading.Lock()  # the warm-up thread and the caller may both ask for the pool first


def _start_pool(workers: int, preload: Sequence[str]) -> _Pool:
    """A new pool of ``workers`` processes forked from the forkserver, each tied to this process."""
    context = multiprocessing.get_context("forkserver")
    # Workers fork from a clean server process that imported the heavy modules once, instead of each
    # spawned worker importing them again; nothing is inherited from this (possibly threaded) process.
    context.set_forkserver_preload(list(preload))
    # The read end travels to each worker with its start arguments; the write end never leaves this process.
    lifeline_read, lifeline_write = context.Pipe(duplex=False)
    pool = ProcessPoolExecutor(
        max_workers=workers, mp_context=context, initializer=_start_worker, initargs=(lifeline_read,)
    )
    return _Pool(os.getpid(), pool, lifeline_write)


def _local_pool(workers: int, preload: Sequence[str] = ()) -> ProcessPoolExecutor:
    """The kept pool of ``workers`` processes, started on first use; a pool whose worker died is replaced."""
    with _POOLS_LOCK:
        kept = _POOLS.get(workers)
        if kept is not None and kept.owner == os.getpid():
            if not getattr(kept.pool, "_broken", False):
                return kept.pool
            kept.close(wait=False)
        if not any(k.owner == os.getpid() for k in _POOLS.values()):
            atexit.register(shutdown_pools)
        _POOLS[workers] = _start_pool(workers, preload)
        return _POOLS[workers].pool


def shutdown_pools() -> None:
    """Stop this process's kept pools (they also stop when it exits)."""
    for workers, kept in list(_POOLS.items()):
        del _POOLS[workers]
        if kept.owner == os.getpid():
            kept.close(wait=True)


def _ready() -> bool:
    return True


def _map_pool(function, items, order, on_done, pool: ProcessPoolExecutor) -> dict:
    results = {}
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


def _map_ray(function, items, order, on_done, ray, resources: TaskResources) -> dict:
    remote = ray.remote(num_cpus=resources.cpus, num_gpus=resources.gpus)(_call)
    function_ref = ray.put(function)  # one copy of the function (and what it binds) for every task
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
