"""A `relightanyone run` killed with SIGKILL in the middle of a stage is finished by the next run, with the
same bytes as an uninterrupted run and nothing duplicated; the stage and its pool workers die with it."""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
from pathlib import Path

from helpers.custom_capture import make_capture
from helpers.held_workers import BUSY, HELD_INGEST_SCRIPT, RELEASE_ENV, release
from helpers.kill_handshake import HANG_GUARD_SECONDS, descendants, kill_all, kill_at, wait_until_dead

from relightanyone.format.reader import NormalizedDataset
from relightanyone.pipelines.dag.runner import STAGE_RECORD_NAME, execute, load_pipeline, plan

# A resumable, deterministic stage: writes parts one by one (each atomically), skipping finished ones, and
# appends one line per part it wrote to a journal outside its output, so duplicated work would show.
# It prints nothing: only the runner's death signal (not a broken pipe) can stop it. When HANDSHAKE_ENV
# names a FIFO, it announces part 3 there and then waits, holding the FIFO open until it dies.
HANDSHAKE_ENV = "STAGE_HANDSHAKE_FIFO"
SLOW_SCRIPT = f"""
import os, pathlib, signal, sys
out, journal, count = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), int(sys.argv[3])
handshake = os.environ.get({HANDSHAKE_ENV!r})
for i in range(count):
    part = out / f"part-{{i:02d}}.txt"
    if part.exists():
        continue
    tmp = part.with_suffix(".tmp")
    tmp.write_text(f"part {{i}}\\n" * 500)
    os.replace(tmp, part)
    with open(journal, "a") as handle:
        handle.write(f"{{i}}\\n")
    if handshake and i == 3:
        fifo = open(handshake, "w")
        fifo.write("PART 3 WRITTEN\\n")
        fifo.flush()
        while True:
            signal.pause()
(out / "summary.txt").write_text("".join(sorted(p.name + "\\n" for p in out.glob("part-*.txt"))))
"""

PIPELINE = """
vars:
  out: unset
stages:
  slow:
    command: ["${{python}}", "-S", "{script}", "${{output}}", "${{out}}/journal.txt", "12"]
    output: ${{out}}/slow
  concat:
    command: ["${{python}}", "-S", "-c", "import sys, pathlib; pathlib.Path(sys.argv[2], 'all.txt').write_text(pathlib.Path(sys.argv[1], 'summary.txt').read_text())", "${{out}}/slow", "${{output}}"]
    inputs: ["${{out}}/slow"]
    output: ${{out}}/concat
"""


def read_fifo(fd: int) -> bytes:
    """What is ready on the FIFO ``fd`` (b"" once every writer has closed it); fails after the hang guard."""
    ready, _, _ = select.select([fd], [], [], HANG_GUARD_SECONDS)
    assert ready, f"nothing happened on the handshake FIFO for {HANG_GUARD_SECONDS} s"
    return os.read(fd, 4096)


def recorded_digest(output: Path) -> str:
    return json.loads((output / STAGE_RECORD_NAME).read_text())["outputs"]["digest"]


def test_sigkill_mid_stage_then_rerun_matches_an_uninterrupted_run(tmp_path):
    script = tmp_path / "slow.py"
    script.write_text(SLOW_SCRIPT)
    pipeline_file = tmp_path / "pipe.yaml"
    pipeline_file.write_text(PIPELINE.format(script=script))

    reference = tmp_path / "reference"
    execute(load_pipeline(pipeline_file, {"out": str(reference)}), echo=None, announce=lambda _: None)

    killed = tmp_path / "killed"
    fifo = tmp_path / "handshake"
    os.mkfifo(fifo)
    # Non-blocking, so that the hang guard applies while no writer has opened the FIFO yet.
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    runner = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "relightanyone",
            "run",
            str(pipeline_file),
            "--var",
            f"out={killed}",
            "--quiet",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        env={**os.environ, HANDSHAKE_ENV: str(fifo)},
    )
    try:
        assert read_fifo(reader) == b"PART 3 WRITTEN\n", "the run ended before its stage reached part 3"
        assert runner.poll() is None
        os.kill(runner.pid, signal.SIGKILL)  # the runner only: its stage must die with it
        runner.wait(timeout=HANG_GUARD_SECONDS)
        # End of file: the stage, the only writer, has closed the FIFO, which it does only by dying.
        assert read_fifo(reader) == b"", "the stage kept running after the runner was killed"
    finally:
        os.close(reader)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(runner.pid, signal.SIGKILL)
        runner.wait()
    assert sorted(p.name for p in (killed / "slow").glob("part-*.txt")) == [
        f"part-{i:02d}.txt" for i in range(4)
    ]
    assert not (killed / "slow" / STAGE_RECORD_NAME).exists()  # a partial run never looks complete
    assert (killed / ".slow_stage.log").exists()  # the live log of the killed stage, beside its output
    pipeline = load_pipeline(pipeline_file, {"out": str(killed)})
    assert [d.reason for d in plan(pipeline)][0] == "no complete _stage.json (never run, or interrupted)"

    results = execute(pipeline, echo=None, announce=lambda _: None)
    assert [r.status for r in results] == ["ran", "ran"]
    for stage in ("slow", "concat"):
        assert recorded_digest(killed / stage) == recorded_digest(reference / stage), stage
    assert not (killed / ".slow_stage.log").exists() and (killed / "slow" / "_stage.log").exists()
    journal = (killed / "journal.txt").read_text().split()
    assert sorted(journal, key=int) == [str(i) for i in range(12)]  # every part written exactly once
    assert [r.status for r in execute(pipeline, echo=None, announce=lambda _: None)] == ["skipped", "skipped"]


INGEST_PIPELINE = """
vars:
  out: unset
stages:
  ingest:
    command: ["${{python}}", "{script}", "{capture}", "${{output}}"]
    output: ${{out}}/normalized
"""


def test_sigkill_of_the_runner_ends_the_stage_and_its_pool_workers(tmp_path):
    capture = make_capture(tmp_path / "capture", subjects=("s1", "s2", "s3"))
    script = tmp_path / "held_ingest.py"
    script.write_text(HELD_INGEST_SCRIPT)
    pipeline_file = tmp_path / "pipe.yaml"
    pipeline_file.write_text(INGEST_PIPELINE.format(script=script, capture=capture))
    out, fifo = tmp_path / "out", tmp_path / "release"
    os.mkfifo(fifo)
    # Not quiet: the runner echoes its stage's output, where the held workers announce themselves.
    runner = subprocess.Popen(
        [sys.executable, "-m", "relightanyone", "run", str(pipeline_file), "--var", f"out={out}"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", RELEASE_ENV: str(fifo)},
    )
    run: dict[int, str] = {}
    try:
        kill_at(runner, BUSY, count=2, before_kill=lambda: run.update(descendants(runner.pid)))
        assert len(run) >= 5, run  # the stage, its forkserver, resource tracker and two workers
        release(fifo)  # a worker that survived would now finish its part
        assert wait_until_dead(run) == [], "processes of the killed run are still alive"
    finally:
        kill_all(run)
    parts = out / "normalized" / "custom" / "_parts"
    assert [p.name for p in parts.iterdir() if p.is_dir() and not p.name.endswith(".tmp")] == []

    results = execute(load_pipeline(pipeline_file, {"out": str(out)}), echo=None, announce=lambda _: None)
    assert [r.status for r in results] == ["ran"]
    dataset = NormalizedDataset(out / "normalized" / "custom")
    assert dataset.manifest.counts["images"] == 24 and dataset.manifest.counts["subjects"] == 3
