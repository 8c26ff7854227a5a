"""A `relightanyone run` killed with SIGKILL in the middle of a stage is finished by the next run, with the
same bytes as an uninterrupted run and nothing duplicated."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from relightanyone.pipelines.dag.runner import STAGE_RECORD_NAME, execute, load_pipeline, plan

# A resumable, deterministic stage: writes parts one by one (each atomically), skipping finished ones, and
# appends one line per part it wrote to a journal outside its output, so duplicated work would show.
# It prints nothing: only the runner's death signal (not a broken pipe) can stop it.
SLOW_SCRIPT = """
import os, pathlib, sys, time
out, journal, count = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), int(sys.argv[3])
for i in range(count):
    part = out / f"part-{i:02d}.txt"
    if part.exists():
        continue
    tmp = part.with_suffix(".tmp")
    tmp.write_text(f"part {i}\\n" * 500)
    os.replace(tmp, part)
    with open(journal, "a") as handle:
        handle.write(f"{i}\\n")
    time.sleep(0.25)
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
    )
    try:
        deadline = time.monotonic() + 120
        while not (killed / "slow" / "part-03.txt").exists():
            assert runner.poll() is None, "the run ended before it could be interrupted"
            assert time.monotonic() < deadline, "the stage never got going"
            time.sleep(0.05)
        os.kill(runner.pid, signal.SIGKILL)  # the runner only: its stage must die with it
        runner.wait(timeout=30)
        time.sleep(0.8)
        parts_after_kill = sorted(p.name for p in (killed / "slow").glob("part-*.txt"))
        time.sleep(0.8)
        assert sorted(p.name for p in (killed / "slow").glob("part-*.txt")) == parts_after_kill, (
            "the stage kept running after the runner was killed"
        )
    finally:
        if runner.poll() is None:
            os.killpg(runner.pid, signal.SIGKILL)
            runner.wait()
    assert 4 <= len(parts_after_kill) < 12
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
