"""An ingest killed with SIGKILL completes on re-run, identical to an uninterrupted run, and leaves no
process behind; a second ingest into a folder being written is refused and touches nothing; Ray gives the
same bytes as the local executor."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers.custom_capture import dataset_bytes, ingest, make_capture
from helpers.held_workers import BUSY, HELD_INGEST_SCRIPT, RELEASE_ENV, release
from helpers.kill_handshake import (
    IMPORT_HELPERS,
    descendants,
    kill_all,
    kill_at,
    start_python,
    wait_until_dead,
)

from relightanyone.cli import cli

# Ingests a capture with one worker (the tasks run in this process, one subject after the other); once the
# first subject's part is published it announces it and waits to be killed: before the next subject and
# before the commit that writes the manifest.
KILLED_INGEST_SCRIPT = IMPORT_HELPERS + textwrap.dedent(
    """
    from pathlib import Path
    from helpers.custom_capture import ingest
    from helpers.kill_handshake import block_until_killed
    from relightanyone.ingest import runner

    run_subject_task = runner.run_subject_task

    def run_then_wait(writer, settings, task):
        run_subject_task(writer, settings, task)
        block_until_killed("PUBLISHED")

    runner.run_subject_task = run_then_wait
    ingest(Path(sys.argv[1]), Path(sys.argv[2]))
    """
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return make_capture(tmp_path_factory.mktemp("resume") / "capture", subjects=("s1", "s2", "s3"))


@pytest.fixture(scope="module")
def reference(capture, tmp_path_factory) -> dict[str, bytes]:
    return dataset_bytes(ingest(capture, tmp_path_factory.mktemp("reference")).path)


def test_sigkill_then_rerun_gives_the_uninterrupted_dataset(capture, reference, tmp_path):
    out = tmp_path / "out"
    kill_at(start_python(KILLED_INGEST_SCRIPT, capture, out), "PUBLISHED")
    parts = out / "custom" / "_parts"
    published = [p.name for p in parts.iterdir() if p.is_dir() and not p.name.endswith(".tmp")]
    assert len(published) == 1 and published[0] in {"s1", "s2", "s3"}, published
    assert not (out / "custom" / "manifest.json").exists()
    summary = ingest(capture, out)
    assert summary.resumed_subjects == 1
    assert dataset_bytes(summary.path) == reference


def test_sigkill_of_an_ingest_leaves_no_worker_and_no_part_published_after_it(capture, reference, tmp_path):
    out, fifo = tmp_path / "out", tmp_path / "release"
    os.mkfifo(fifo)
    child = start_python(HELD_INGEST_SCRIPT, capture, out, env={RELEASE_ENV: str(fifo)})
    run: dict[int, str] = {}
    try:
        # Both workers hold a subject's unfinished part; the forkserver and the resource tracker run too.
        kill_at(child, BUSY, count=2, before_kill=lambda: run.update(descendants(child.pid)))
        assert len(run) >= 3, run
        release(fifo)  # a worker that survived would now finish its part
        assert wait_until_dead(run) == [], "processes of the killed ingest are still alive"
    finally:
        kill_all(run)
    parts = out / "custom" / "_parts"
    assert [p.name for p in parts.iterdir() if p.is_dir() and not p.name.endswith(".tmp")] == []
    summary = ingest(capture, out)
    assert summary.resumed_subjects == 0
    assert dataset_bytes(summary.path) == reference


def _files(root: Path) -> dict[str, tuple[int, int, bytes]]:
    """Every file under ``root``: relative path -> (size, modification time, bytes)."""
    return {
        str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_a_second_ingest_into_a_folder_being_written_fails_naming_the_writer(capture, reference, tmp_path):
    out = tmp_path / "out"
    args = ["ingest", "custom", str(capture), "--out", str(out), "--template", str(capture / "template.obj")]
    first = start_python(KILLED_INGEST_SCRIPT, capture, out)
    refused = {}

    def second_ingest_while_the_first_writes() -> None:
        before = _files(out)
        refused["result"] = CliRunner().invoke(cli, [*args, "--preset", "tiny"])
        refused["unchanged"] = _files(out) == before

    kill_at(first, "PUBLISHED", before_kill=second_ingest_while_the_first_writes)
    result = refused["result"]
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1, result.output
    assert f"pid {first.pid} on " in lines[0] and str(out / "custom") in lines[0], lines
    assert refused["unchanged"]  # nothing of the first run was touched
    # The kill released the lock: the next ingest resumes the first one's work.
    again = CliRunner().invoke(cli, [*args, "--preset", "tiny"])
    assert again.exit_code == 0, again.output
    assert dataset_bytes(out / "custom") == reference


@pytest.mark.ray
@pytest.mark.usefixtures("ray_exclusive")
def test_ray_executor_gives_the_same_bytes(capture, reference, tmp_path):
    ray = pytest.importorskip("ray", reason="the ray extra is not installed")
    try:
        summary = ingest(capture, tmp_path / "out", workers=2, executor="ray")
        assert ray.cluster_resources()["CPU"] == 2  # no cluster address: a local Ray of ``workers`` CPUs
    finally:
        ray.shutdown()
    assert dataset_bytes(summary.path) == reference
