"""An ingest killed with SIGKILL completes on re-run, identical to an uninterrupted run; Ray gives the
same bytes as the local executor."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from pathlib import Path

import pytest
from test_ingest_core_faults import dataset_bytes, ingest, make_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return make_capture(tmp_path_factory.mktemp("resume") / "capture", subjects=("s1", "s2", "s3"))


@pytest.fixture(scope="module")
def reference(capture, tmp_path_factory) -> dict[str, bytes]:
    return dataset_bytes(ingest(capture, tmp_path_factory.mktemp("reference")).path)


def _ingest_in_child(capture: Path, out: Path) -> None:
    ingest(capture, out)


def test_sigkill_then_rerun_gives_the_uninterrupted_dataset(capture, reference, tmp_path):
    out = tmp_path / "out"
    parts = out / "custom" / "_parts"
    child = multiprocessing.get_context("fork").Process(target=_ingest_in_child, args=(capture, out))
    child.start()
    deadline = time.monotonic() + 300
    # Kill once the first subject's part is published and before the commit writes the manifest.
    while time.monotonic() < deadline and child.is_alive():
        if parts.is_dir() and any(p.is_dir() and not p.name.endswith(".tmp") for p in parts.iterdir()):
            break
        time.sleep(0.02)
    assert child.is_alive(), "the ingest finished before it could be killed"
    os.kill(child.pid, signal.SIGKILL)
    child.join()
    assert child.exitcode == -signal.SIGKILL
    assert not (out / "custom" / "manifest.json").exists()
    summary = ingest(capture, out)
    assert summary.resumed_subjects >= 1
    assert dataset_bytes(summary.path) == reference


@pytest.mark.ray
def test_ray_executor_gives_the_same_bytes(capture, reference, tmp_path):
    ray = pytest.importorskip("ray", reason="the ray extra is not installed")
    try:
        summary = ingest(capture, tmp_path / "out", workers=2, executor="ray")
        assert ray.cluster_resources()["CPU"] == 2  # no cluster address: a local Ray of ``workers`` CPUs
    finally:
        ray.shutdown()
    assert dataset_bytes(summary.path) == reference
