"""The executor: the same results in this process and in the kept local pool; the pool is kept between
maps, can be started ahead of the tasks and is replaced when broken; Ray joins a cluster or starts a local
one; each task gets its share of the CPUs. Ingest and the expansion check byte-identical datasets on every
executor, Ray included, in their own tests."""

from __future__ import annotations

import hashlib
import os
import sys
import types

import numpy as np
import pytest

from relightanyone import parallel
from relightanyone.errors import InputError
from relightanyone.parallel import Executor, cpu_share, ray_init_arguments, shutdown_pools


def _pid(_item) -> int:
    return os.getpid()


def _die(item) -> int:
    if item == "die":
        os._exit(3)  # a worker lost mid-task (out of memory, killed)
    return os.getpid()


def _digest(item: int) -> str:
    """Float work whose bytes would show any difference between processes."""
    values = np.random.default_rng(item).normal(size=(64, 64)).astype(np.float32)
    return hashlib.sha256((values @ values.T).tobytes()).hexdigest()


def test_pool_workers_are_kept_between_calls_and_a_broken_pool_is_replaced():
    pool = Executor("local", 2)
    try:
        first = set(pool.map(_pid, list(range(6))))
        second = set(pool.map(_pid, list(range(6))))
        assert os.getpid() not in first
        assert second <= first  # the same warm workers, not new ones
        with pytest.raises(Exception, match="terminated abruptly"):
            pool.map(_die, ["die", "x"])
        after = set(pool.map(_pid, list(range(6))))
        assert after and not (after & first)  # a fresh pool took over
    finally:
        shutdown_pools()


def test_warmed_pool_is_the_one_the_tasks_run_on():
    try:
        assert Executor("local", 1).warm() is None  # one worker runs in this process: nothing to start
        assert Executor("ray", 2).warm() is None
        thread = Executor("local", 2).warm()
        thread.join(timeout=120)
        assert not thread.is_alive()
        warmed = parallel._POOLS[2].pool
        pids = set(Executor("local", 2).map(_pid, list(range(6))))
        assert parallel._POOLS[2].pool is warmed  # no second pool was started
        assert pids and os.getpid() not in pids
        assert {p.pid for p in warmed._processes.values()} >= pids
    finally:
        shutdown_pools()


def test_in_process_map_keeps_item_order_runs_here_and_starts_the_costliest_first():
    assert Executor("local", 1).map(_pid, [1, 2, 3]) == [os.getpid()] * 3
    assert Executor("local", 4).in_process(1) and not Executor("local", 4).in_process(2)
    finished = []
    results = Executor().map(
        lambda x: x * 10, [1, 5, 3, 5], on_done=finished.append, cost=lambda x: x
    )  # ties keep item order
    assert results == [10, 50, 30, 50] and finished == [5, 5, 3, 1]


def test_pool_and_in_process_give_the_same_results_in_item_order():
    items = list(range(7))
    try:
        here = Executor().map(_digest, items)
        assert Executor("local", 2).map(_digest, items, cost=lambda i: i % 3) == here
    finally:
        shutdown_pools()


def test_ray_joins_a_given_cluster_as_it_is_or_starts_a_local_one():
    """The arguments only: a Ray task's results are checked by the ingest and expansion Ray tests."""
    assert ray_init_arguments(None, 3, {}) == {
        "num_cpus": 3,
        "include_dashboard": False,
        "log_to_driver": False,
    }
    joined = {"address": "ray://head:10001", "log_to_driver": False}
    assert ray_init_arguments("ray://head:10001", 3, {}) == joined
    assert ray_init_arguments(None, 3, {"RAY_ADDRESS": "ray://head:10001"}) == joined
    assert ray_init_arguments("auto", 3, {"RAY_ADDRESS": "ray://other:1"})["address"] == "auto"
    assert "num_cpus" not in ray_init_arguments(None, 3, {"RAY_ADDRESS": "auto"})


def test_a_process_that_ran_a_local_ray_refuses_to_join_a_cluster(monkeypatch):
    """Ray loses a cluster joined after a local Ray in the same process; the executor says so instead of
    letting the tasks fail. A stand-in Ray records what it is asked."""
    started = []
    fake_ray = types.SimpleNamespace(is_initialized=lambda: False, init=lambda **kw: started.append(kw))
    monkeypatch.setitem(sys.modules, "ray", fake_ray)
    monkeypatch.setattr(parallel, "_local_ray_started", False)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    Executor("ray", 2)._ray()
    assert started == [ray_init_arguments(None, 2, {})]
    with pytest.raises(InputError, match="already started a local Ray.*127.0.0.1:6379.*new process"):
        Executor("ray", 2, address="127.0.0.1:6379")._ray()
    assert len(started) == 1


def test_bad_executors_are_named():
    with pytest.raises(ValueError, match="unknown executor 'dask'"):
        Executor("dask", 2)
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        Executor("local", 0)


def test_each_task_gets_its_share_of_the_cpus():
    cpus = len(os.sched_getaffinity(0))
    assert cpu_share(1) == cpus == Executor("local", 1).cpu_share()
    assert cpu_share(cpus) == 1
    assert cpu_share(4 * cpus) == 1
    assert cpu_share(1, "ray") == 1 == Executor("ray", 1).cpu_share()
