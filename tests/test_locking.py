"""One writer per output folder: every writer that owns a folder refuses, in one line naming the other
process, a folder that process is writing, and changes nothing in it; a dead holder's lock is free."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

from click.testing import CliRunner
from helpers.kill_handshake import IMPORT_HELPERS, kill_at, start_python

from relightanyone.cli import cli
from relightanyone.format.examples import write_example_dataset
from relightanyone.locking import LOCK_NAME, OutputLockedError, acquire_output_lock, output_lock
from relightanyone.pipelines.dag.record import stage_lock_name

# Takes the lock of each (folder, lock file name) pair given as arguments, then waits to be killed.
HOLDER_SCRIPT = IMPORT_HELPERS + textwrap.dedent(
    """
    from helpers.kill_handshake import block_until_killed
    from relightanyone.locking import acquire_output_lock

    pairs = sys.argv[1:]
    for folder, name in zip(pairs[::2], pairs[1::2]):
        acquire_output_lock(folder, name)
    block_until_killed("LOCKED")
    """
)

PIPELINE = """
stages:
  touch:
    command: ["${{python}}", "-c", "import pathlib, sys; pathlib.Path(sys.argv[1], 'done').write_text('')", "${{output}}"]
    output: {output}
"""


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_writers_refuse_a_folder_another_process_writes_and_take_it_once_that_process_died(tmp_path):
    dataset = write_example_dataset(tmp_path / "data", subjects=("s000",))
    export_out, run_out, pipe_out = tmp_path / "export", tmp_path / "run", tmp_path / "pipe" / "out"
    pipeline_file = tmp_path / "pipe.yaml"
    pipeline_file.write_text(PIPELINE.format(output=pipe_out))
    commands = {
        "export-dataset": ["export-dataset", str(dataset), "--out", str(export_out)],
        "train stage1": [
            "train",
            "stage1",
            "--data",
            str(dataset),
            "--out",
            str(run_out),
            "--iterations",
            "1",
        ],
        "train stage2": ["train", "stage2", "--data", str(dataset), "--single-stage", "--out", str(run_out)],
        "run": ["run", str(pipeline_file)],
    }
    held = [export_out, LOCK_NAME, run_out, LOCK_NAME, pipe_out.parent, stage_lock_name(pipe_out)]
    holder = start_python(HOLDER_SCRIPT, *held)
    refusals = {}

    def write_while_held() -> None:
        before = _files(tmp_path)
        for what, args in commands.items():
            result = CliRunner().invoke(cli, args)
            refusals[what] = (result.exit_code, result.stderr.strip().splitlines())
        refusals["unchanged"] = _files(tmp_path) == before

    kill_at(holder, "LOCKED", before_kill=write_while_held)
    assert refusals.pop("unchanged")
    for what, (status, lines) in refusals.items():
        assert status == 1 and len(lines) == 1, (what, lines)
        assert f"another run is writing here (pid {holder.pid} on " in lines[0], (what, lines)
    # The holder is dead: its locks are free, and a finished writer removes its lock file.
    assert CliRunner().invoke(cli, commands["export-dataset"]).exit_code == 0
    assert (export_out / "dataset.json").is_file() and not (export_out / LOCK_NAME).exists()
    assert CliRunner().invoke(cli, commands["run"]).exit_code == 0
    assert (pipe_out / "done").is_file() and not (pipe_out.parent / stage_lock_name(pipe_out)).exists()


def test_a_process_may_take_its_own_lock_again_and_only_the_first_taker_releases_it(tmp_path):
    with output_lock(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text().startswith(f"pid {os.getpid()} on ")
        with output_lock(tmp_path):
            assert acquire_output_lock(tmp_path) is False
        assert (tmp_path / LOCK_NAME).exists()
    assert not (tmp_path / LOCK_NAME).exists()
    assert issubclass(OutputLockedError, ValueError)
