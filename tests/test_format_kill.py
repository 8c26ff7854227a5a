"""A writer killed with SIGKILL leaves an incomplete dataset that readers refuse; re-running it gives the
bytes of an uninterrupted run."""

from __future__ import annotations

import hashlib
import textwrap
from pathlib import Path

import pytest
from helpers.kill_handshake import IMPORT_HELPERS, finish, kill_at, start_python

from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
from relightanyone.format.validate import validate_path

# Writes the example dataset with small shards; in "pause-commit" mode it announces itself and waits to be
# killed while writing the second row of the second shard, in "pause-task" mode while writing the second task.
WRITER_SCRIPT = IMPORT_HELPERS + textwrap.dedent(
    """
    from pathlib import Path
    from helpers.kill_handshake import block_until_killed
    from relightanyone.format import arrow_io
    from relightanyone.format.examples import write_example_dataset

    root, mode = Path(sys.argv[1]), sys.argv[2]
    original_write = arrow_io.StreamFileWriter.write
    original_write_message = arrow_io.StreamFileWriter.write_message

    def pause_here(self):
        in_commit = self.path.name == "images-00001.arrow" and len(self.offsets) == 1
        in_task = self.path.parent.name == "s001.tmp" and len(self.offsets) == 2
        if (mode == "pause-commit" and in_commit) or (mode == "pause-task" and in_task):
            block_until_killed("PAUSED")

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


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> dict[str, str]:
    root = tmp_path_factory.mktemp("uninterrupted")
    finish(start_python(WRITER_SCRIPT, root, "straight"), "DONE")
    return _digests(root / "demo")


@pytest.mark.parametrize("mode", ["pause-commit", "pause-task"])
def test_sigkill_mid_write_then_rerun_is_byte_identical(tmp_path, uninterrupted, mode):
    kill_at(start_python(WRITER_SCRIPT, tmp_path, mode), "PAUSED")
    dataset_dir = tmp_path / "demo"
    leftovers = {p.name for p in dataset_dir.iterdir()}
    assert "manifest.json" not in leftovers
    if mode == "pause-commit":
        assert {"images-00000.arrow", "images-00001.arrow.tmp", "_parts"} <= leftovers
    with pytest.raises(IncompleteDatasetError, match="incomplete"):
        NormalizedDataset(dataset_dir)
    problems = validate_path(tmp_path)
    assert problems and "no manifest.json" in str(problems[0]) and "incomplete" in str(problems[0])

    finish(start_python(WRITER_SCRIPT, tmp_path, "straight"), "DONE")
    assert _digests(dataset_dir) == uninterrupted
    assert validate_path(dataset_dir) == []
