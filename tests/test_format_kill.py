"""A writer killed with SIGKILL leaves an incomplete dataset that readers refuse; re-running it gives the
bytes of an uninterrupted run."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
from relightanyone.format.validate import validate_path

# Writes the example dataset with small shards; in "pause-commit" mode it announces itself and sleeps
# while writing the second row of the second shard, in "pause-task" mode while writing the second task.
WRITER_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from relightanyone.format import arrow_io, shards
    from relightanyone.format.examples import write_example_dataset

    root, mode = Path(sys.argv[1]), sys.argv[2]
    original_write = arrow_io.StreamFileWriter.write
    original_write_message = arrow_io.StreamFileWriter.write_message

    def pause_here(self):
        in_commit = self.path.name == "images-00001.arrow" and len(self.offsets) == 1
        in_task = self.path.parent.name == "s001.tmp" and len(self.offsets) == 2
        if (mode == "pause-commit" and in_commit) or (mode == "pause-task" and in_task):
            print("PAUSED", flush=True)
            time.sleep(120)

    def pausing_write(self, batch):
        pause_here(self)
        return original_write(self, batch)

    def pausing_write_message(self, message):
        pause_here(self)
        return original_write_message(self, message)

    arrow_io.StreamFileWriter.write = pausing_write
    arrow_io.StreamFileWriter.write_message = pausing_write_message
    write_example_dataset(root, max_shard_bytes=20_000)
    print("DONE", flush=True)
    """
)


def _run_writer(root: Path, mode: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", WRITER_SCRIPT, str(root), mode],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> dict[str, str]:
    root = tmp_path_factory.mktemp("uninterrupted")
    process = _run_writer(root, "straight")
    assert process.communicate(timeout=120)[0].strip().endswith("DONE")
    return _digests(root / "demo")


@pytest.mark.parametrize("mode", ["pause-commit", "pause-task"])
def test_sigkill_mid_write_then_rerun_is_byte_identical(tmp_path, uninterrupted, mode):
    process = _run_writer(tmp_path, mode)
    try:
        assert process.stdout.readline().strip() == "PAUSED"
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
    assert process.returncode == -signal.SIGKILL
    dataset_dir = tmp_path / "demo"
    leftovers = {p.name for p in dataset_dir.iterdir()}
    assert "manifest.json" not in leftovers
    if mode == "pause-commit":
        assert {"images-00000.arrow", "images-00001.arrow.tmp", "_parts"} <= leftovers
    with pytest.raises(IncompleteDatasetError, match="incomplete"):
        NormalizedDataset(dataset_dir)
    problems = validate_path(tmp_path)
    assert problems and "no manifest.json" in str(problems[0]) and "incomplete" in str(problems[0])

    rerun = _run_writer(tmp_path, "straight")
    assert rerun.communicate(timeout=120)[0].strip().endswith("DONE")
    assert _digests(dataset_dir) == uninterrupted
    assert validate_path(dataset_dir) == []
