"""The local executor keeps its process pool between calls, can start it ahead of the tasks, and replaces a
broken one; the template cache,
which pool workers keep across ingests, follows the file it was read from."""

from __future__ import annotations

import os

import numpy as np
import pytest

from relightanyone.ingest.executors import map_items, shutdown_pools, warm_local_pool
from relightanyone.ingest.tracking import load_template
from relightanyone.synth.template import make_template, write_obj, write_template


def _pid(_item) -> int:
    return os.getpid()


def _die(item) -> int:
    if item == "die":
        os._exit(3)  # a worker lost mid-task (out of memory, killed)
    return os.getpid()


def test_pool_workers_are_kept_between_calls_and_a_broken_pool_is_replaced():
    try:
        first = set(map_items(_pid, list(range(6)), workers=2))
        second = set(map_items(_pid, list(range(6)), workers=2))
        assert os.getpid() not in first
        assert second <= first  # the same warm workers, not new ones
        with pytest.raises(Exception, match="terminated abruptly"):
            map_items(_die, ["die", "x"], workers=2)
        after = set(map_items(_pid, list(range(6)), workers=2))
        assert after and not (after & first)  # a fresh pool took over
    finally:
        shutdown_pools()


def test_warmed_pool_is_the_one_the_tasks_run_on():
    try:
        assert warm_local_pool(1) is None  # one worker runs in this process: nothing to start
        thread = warm_local_pool(2)
        thread.join(timeout=120)
        assert not thread.is_alive()
        from relightanyone.ingest import executors

        warmed = executors._POOLS[2][1]
        pids = set(map_items(_pid, list(range(6)), workers=2))
        assert executors._POOLS[2][1] is warmed  # no second pool was started
        assert pids and os.getpid() not in pids
        assert {p.pid for p in warmed._processes.values()} >= pids
    finally:
        shutdown_pools()


def test_in_process_map_keeps_item_order_and_runs_here():
    assert map_items(_pid, [1, 2, 3], workers=1) == [os.getpid()] * 3


def test_cached_template_is_reread_when_the_file_changes(tmp_path):
    template = make_template(12)
    write_template(tmp_path, template)
    first = load_template(tmp_path / "template.obj")
    assert load_template(tmp_path / "template.obj") is first  # cached while unchanged
    moved = template.vertices + np.array([0.0, 0.01, 0.0])
    write_obj(tmp_path / "template.obj", moved, template.faces, template.uvs, template.face_uvs)
    os.utime(tmp_path / "template.obj", ns=(1, 1))  # a different signature even within one clock tick
    second = load_template(tmp_path / "template.obj")
    assert np.allclose(second.vertices, moved, atol=1e-8)
    (tmp_path / "neck_mask.txt").write_text("\n".join("0" for _ in moved) + "\n")
    os.utime(tmp_path / "neck_mask.txt", ns=(2, 2))
    assert not load_template(tmp_path / "template.obj").neck_vertices.any()
