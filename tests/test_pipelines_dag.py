"""The staged DAG runner: skipping, re-running on changes, --force, --dry-run, YAML errors.

Stages are small `command:` steps running a Python script, so every test runs real subprocesses in well
under a second each.
"""

from __future__ import annotations

import json
import os
import textwrap
from pathlib import Path

import pytest
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.pipelines.cli import run_command
from relightanyone.pipelines.dag.fingerprint import HashCache, fingerprint_path
from relightanyone.pipelines.dag.pipeline_file import PipelineError
from relightanyone.pipelines.dag.runner import (
    STAGE_LOG_NAME,
    STAGE_RECORD_NAME,
    StageFailed,
    execute,
    load_hash_cache,
    load_pipeline,
    plan,
    read_record,
)

STEP_SCRIPT = """
import pathlib, sys
out, value, note, *inputs = sys.argv[1:]
if value == "fail":
    print("failing on purpose", flush=True)
    sys.exit(3)
if value.startswith("resumable"):
    # Like a trainer with a checkpoint: work already in the folder is kept, not redone.
    done = pathlib.Path(out) / "checkpoint.txt"
    if not done.exists():
        done.write_text(value)
        if value.endswith("-crash"):
            print("crashed after the checkpoint", flush=True)
            sys.exit(4)
    (pathlib.Path(out) / "result.txt").write_text(done.read_text())
    print("wrote", out, flush=True)
    sys.exit(0)
text = value + "".join(pathlib.Path(p).read_text() for p in inputs)
(pathlib.Path(out) / "result.txt").write_text(text)
print("wrote", out, flush=True)
"""

PIPELINE = """
vars:
  out: {out}
  value: "1"
  note: a
  step: {step}
stages:
  make:
    command: ["${{python}}", "-S", "${{step}}", "${{output}}", "${{value}}", "${{note}}", "{external}"]
    inputs: ["{external}"]
    output: ${{out}}/make
  double:
    command: ["${{python}}", "-S", "${{step}}", "${{output}}", "dbl", "-", "${{out}}/make/result.txt"]
    inputs: ["${{out}}/make"]
    output: ${{out}}/double
  side:
    command: ["${{python}}", "-S", "${{step}}", "${{output}}", "side", "-"]
    output: ${{out}}/side
"""


@pytest.fixture()
def pipeline_file(tmp_path: Path) -> Path:
    step = tmp_path / "step.py"
    step.write_text(STEP_SCRIPT)
    external = tmp_path / "external.txt"
    external.write_text("ext")
    path = tmp_path / "pipe.yaml"
    path.write_text(PIPELINE.format(out=tmp_path / "out", step=step, external=external))
    return path


def run(path: Path, force=(), only=(), **variables):
    results = execute(
        load_pipeline(path, variables), force=force, only=only, echo=None, announce=lambda _: None
    )
    return {r.stage: r for r in results}


def statuses(results) -> dict[str, str]:
    return {name: r.status for name, r in results.items()}


def test_first_run_runs_everything_and_second_skips_everything(pipeline_file):
    first = run(pipeline_file)
    assert statuses(first) == {"make": "ran", "double": "ran", "side": "ran"}
    out = pipeline_file.parent / "out"
    assert (out / "double" / "result.txt").read_text() == "dbl1ext"
    second = run(pipeline_file)
    assert statuses(second) == {"make": "skipped", "double": "skipped", "side": "skipped"}
    assert {r.reason for r in second.values()} == {"up to date"}


def test_stage_record_holds_config_inputs_outputs_and_times(pipeline_file):
    run(pipeline_file)
    out = pipeline_file.parent / "out"
    record = json.loads((out / "double" / STAGE_RECORD_NAME).read_text())
    assert record["status"] == "complete"
    assert record["config"]["kind"] == "command" and record["config"]["args"][3:] == [
        str(out / "double"),
        "dbl",
        "-",
        str(out / "make/result.txt"),
    ]
    assert list(record["inputs"]) == [str(out / "make")]
    make_record = read_record(out / "make")
    assert record["inputs"][str(out / "make")]["digest"] == make_record["outputs"]["digest"]
    assert "files" not in record["inputs"][str(out / "make")]  # produced by a stage: its record has them
    external = json.loads((out / "make" / STAGE_RECORD_NAME).read_text())["inputs"]
    assert list(next(iter(external.values()))["files"]) == ["."]  # an external file keeps its cache entry
    assert list(record["outputs"]["files"]) == ["result.txt"]
    assert record["package_version"] and record["started"] <= record["finished"]
    assert "wrote" in (out / "double" / STAGE_LOG_NAME).read_text()


def test_config_change_reruns_the_stage_and_downstream_when_its_output_changes(pipeline_file):
    run(pipeline_file)
    results = run(pipeline_file, value="2")
    assert statuses(results) == {"make": "ran", "double": "ran", "side": "skipped"}
    assert results["make"].reason == "config changed"
    assert results["double"].reason.startswith("input ") and results["double"].reason.endswith(" changed")
    assert (pipeline_file.parent / "out/double/result.txt").read_text() == "dbl2ext"


def test_config_change_with_identical_output_leaves_downstream_skipped(pipeline_file):
    run(pipeline_file)
    results = run(pipeline_file, note="b")  # the note changes the command line, not the bytes written
    assert statuses(results) == {"make": "ran", "double": "skipped", "side": "skipped"}


def test_external_input_change_reruns(pipeline_file):
    run(pipeline_file)
    (pipeline_file.parent / "external.txt").write_text("new")
    results = run(pipeline_file)
    assert results["make"].status == "ran"
    assert results["make"].reason == f"input {pipeline_file.parent / 'external.txt'} changed"
    assert (pipeline_file.parent / "out/double/result.txt").read_text() == "dbl1new"


def test_tampered_or_missing_output_reruns(pipeline_file):
    run(pipeline_file)
    out = pipeline_file.parent / "out"
    (out / "side" / "result.txt").write_text("edited")
    (out / "double" / "result.txt").unlink()
    results = run(pipeline_file)
    assert results["side"].status == "ran" and "modified: result.txt" in results["side"].reason
    assert results["double"].status == "ran" and "missing: result.txt" in results["double"].reason
    assert results["make"].status == "skipped"
    assert (out / "side" / "result.txt").read_text() == "side"


def test_a_stage_that_runs_again_does_not_resume_work_of_another_config(pipeline_file):
    make = pipeline_file.parent / "out" / "make"
    run(pipeline_file, value="resumable-a")
    assert (make / "result.txt").read_text() == "resumable-a"
    # Changed config: the completed output is stale, so the command's own resume finds nothing to keep.
    assert run(pipeline_file, value="resumable-b")["make"].reason == "config changed"
    assert (make / "result.txt").read_text() == "resumable-b"
    # --force means "do it again", not "resume the finished run".
    (make / "checkpoint.txt").write_text("stale")
    (make / "extra.txt").write_text("left by the old run")
    run(pipeline_file, value="resumable-b", force=["make"])
    assert (make / "result.txt").read_text() == "resumable-b" and not (make / "extra.txt").exists()


def test_an_interrupted_stage_resumes_its_own_work_but_not_another_configs(pipeline_file):
    make = pipeline_file.parent / "out" / "make"
    with pytest.raises(StageFailed, match="exit status 4"):
        run(pipeline_file, value="resumable-x-crash")
    assert (make / "checkpoint.txt").read_text() == "resumable-x-crash"
    # The same config again: the partial work is resumed (the checkpoint is not redone).
    results = run(pipeline_file, value="resumable-x-crash")
    assert results["make"].reason.startswith("no complete _stage.json")
    assert (make / "result.txt").read_text() == "resumable-x-crash"
    assert not list(make.parent.glob(".make_stage.attempt*"))  # a finished run leaves no attempt marker
    # Interrupted under one config, run again under another: the partial work is not reused.
    with pytest.raises(StageFailed):
        run(pipeline_file, value="resumable-y-crash", force=["make"])
    run(pipeline_file, value="resumable-z")
    assert (make / "result.txt").read_text() == "resumable-z"


def test_a_stale_output_that_is_too_broad_is_not_deleted(tmp_path):
    step = tmp_path / "step.py"
    step.write_text(STEP_SCRIPT)
    path = tmp_path / "pipe.yaml"
    path.write_text(
        textwrap.dedent(
            f"""
            vars:
              value: "1"
            stages:
              make:
                command: ["${{python}}", "-S", "{step}", "${{output}}", "${{value}}", "-"]
                output: {tmp_path}
            """
        )
    )
    run(path)
    with pytest.raises(StageFailed, match="too broad a folder to clear"):
        run(path, value="2")  # its output holds the pipeline file itself
    assert path.exists() and step.exists()


def test_force_reruns_the_stage_and_everything_downstream(pipeline_file):
    run(pipeline_file)
    results = run(pipeline_file, force=["make"])
    assert statuses(results) == {"make": "ran", "double": "ran", "side": "skipped"}
    assert results["double"].reason == "downstream of forced stage make"
    with pytest.raises(PipelineError, match="--force nope: no such stage"):
        run(pipeline_file, force=["nope"])


def test_only_runs_selected_stages_and_needs_completed_upstream(pipeline_file):
    with pytest.raises(StageFailed, match="needs stage 'make'"):
        run(pipeline_file, only=["double"])
    results = run(pipeline_file, only=["make"])
    assert statuses(results) == {"make": "ran", "double": "not selected", "side": "not selected"}
    assert statuses(run(pipeline_file, only=["double"]))["double"] == "ran"


def test_dry_run_prints_the_plan_and_runs_nothing(pipeline_file):
    runner = CliRunner()
    result = runner.invoke(run_command, [str(pipeline_file), "--dry-run"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].split()[:2] == ["run", "make"] and "output missing" in lines[0]
    assert lines[1].split()[:2] == ["run", "double"] and "upstream stage make runs first" in lines[1]
    assert not (pipeline_file.parent / "out").exists()
    assert runner.invoke(run_command, [str(pipeline_file), "--quiet"]).exit_code == 0
    (pipeline_file.parent / "external.txt").write_text("changed")
    result = runner.invoke(run_command, [str(pipeline_file), "--dry-run", "--var", "note=z"])
    assert "run   make    config changed" in result.output
    assert "skip  side    up to date" in result.output
    assert "dry run: 2 of 3 stage(s) would run" in result.output
    assert (pipeline_file.parent / "out/make/result.txt").read_text() == "1ext"  # nothing was run


def test_run_command_streams_stage_output_and_reports_failures(pipeline_file):
    runner = CliRunner()
    result = runner.invoke(run_command, [str(pipeline_file)])
    assert result.exit_code == 0, result.output
    assert "[1/3] make: running (output missing)" in result.output
    assert f"wrote {pipeline_file.parent / 'out' / 'make'}" in result.output  # the stage's own output
    assert result.output.splitlines()[-3].split()[:2] == ["make", "ran"]
    failed = runner.invoke(cli, ["run", str(pipeline_file), "--var", "value=fail", "--quiet"])
    assert failed.exit_code == 1
    assert "stage 'make' failed with exit status 3" in failed.output and "_stage.log" in failed.output


def test_failed_stage_leaves_no_record_and_keeps_its_log(pipeline_file):
    run(pipeline_file)
    with pytest.raises(StageFailed, match="'make' failed with exit status 3"):
        run(pipeline_file, value="fail")
    make = pipeline_file.parent / "out" / "make"
    assert not (make / STAGE_RECORD_NAME).exists()
    assert "failing on purpose" in (make / STAGE_LOG_NAME).read_text()
    assert run(pipeline_file)["make"].reason.startswith("no complete _stage.json")


def test_cached_hashes_are_reused_and_changed_files_rehashed(pipeline_file):
    run(pipeline_file)
    pipeline = load_pipeline(pipeline_file)
    cache = load_hash_cache(pipeline)
    decisions = plan(pipeline, cache=cache)
    assert [d.run for d in decisions] == [False, False, False]
    assert cache.hashed_files == 0  # every file was known by (path, size, mtime_ns)
    fresh = HashCache()
    assert (
        fingerprint_path(pipeline_file.parent / "out", fresh).digest
        == fingerprint_path(pipeline_file.parent / "out", cache).digest
    )
    assert fresh.hashed_files == 3  # the three result.txt; _stage.json and _stage.log are excluded


def test_touched_but_unchanged_files_are_rehashed_once(pipeline_file):
    run(pipeline_file)
    external = pipeline_file.parent / "external.txt"
    os.utime(external, ns=(1_000_000_000, 1_000_000_000))  # new mtime, same bytes
    assert statuses(run(pipeline_file)) == {"make": "skipped", "double": "skipped", "side": "skipped"}
    cache = load_hash_cache(load_pipeline(pipeline_file))
    plan(load_pipeline(pipeline_file), cache=cache)
    assert cache.hashed_files == 0  # the skipped stage's record was refreshed with the new mtime


def write_yaml(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def test_cycle_is_an_error_naming_stages_and_lines(tmp_path):
    path = write_yaml(
        tmp_path,
        """\
        stages:
          a:
            command: [echo, a]
            inputs: [out/b]
            output: out/a
          b:
            command: [echo, b]
            after: [a]
            output: out/b
        """,
    )
    with pytest.raises(PipelineError, match=r"cycle: a -> b -> a.*a \(line 2\), b \(line 6\)"):
        load_pipeline(path)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            "  a:\n    command: [echo]\n    after: [zz]\n    output: o/a\n",
            r"bad.yaml:4 stages.a.after\[0\]: unknown stage 'zz'",
        ),
        (
            "  a:\n    command: [echo, '${nope}']\n    output: o/a\n",
            r"bad.yaml:3 stages.a.command: unknown variable \$\{nope\}",
        ),
        (
            "  a:\n    command: [echo]\n    output: o/a\n  b:\n    run: [x]\n    output: o/a/b\n",
            "overlaps the output of stage 'a'",
        ),
        ("  a:\n    command: [echo]\n    outptu: o/a\n", r"bad.yaml:4 stages.a.outptu: unknown key"),
        ("  a:\n    command: [echo]\n    run: [x]\n    output: o/a\n", "exactly one of run:"),
        ("  a:\n    command: [echo]\n    inputs: [o/a/x]\n    output: o/a\n", "cannot read what it writes"),
    ],
)
def test_malformed_pipelines_are_errors_with_file_line_and_key(tmp_path, body, message):
    path = write_yaml(tmp_path, "stages:\n" + body)
    with pytest.raises(PipelineError, match=message):
        load_pipeline(path)


def test_variables_defaults_overrides_and_references(tmp_path):
    path = write_yaml(
        tmp_path,
        """\
        vars:
          out: o
          sub: ${out}/sub
          price: $$5
        stages:
          a:
            command: [echo, "${sub}", "${price}", "${stage}"]
            output: ${sub}/a
        """,
    )
    stage = load_pipeline(path).stages["a"]
    assert stage.args == ("echo", "o/sub", "$5", "a")
    overridden = load_pipeline(path, {"out": str(tmp_path / "x")}).stages["a"]
    assert overridden.output == tmp_path / "x" / "sub" / "a"
    with pytest.raises(PipelineError, match=r"--var ot: .* has no such variable \(vars: out, sub, price\)"):
        load_pipeline(path, {"ot": "typo"})
    with pytest.raises(PipelineError, match="loop"):
        load_pipeline(
            write_yaml(
                tmp_path, "vars:\n  a: ${b}\n  b: ${a}\nstages:\n  s:\n    command: [x]\n    output: o\n"
            )
        )


def test_shipped_pipelines_load_and_plan(tmp_path):
    for name in ("demo", "real"):
        path = Path(__file__).resolve().parents[1] / "pipelines" / f"{name}.yaml"
        pipeline = load_pipeline(path, {"out": str(tmp_path / name)})
        assert pipeline.order, name
    demo = load_pipeline(
        Path(__file__).resolve().parents[1] / "pipelines" / "demo.yaml", {"out": str(tmp_path)}
    )
    assert demo.order[0] == "world"
    assert set(demo.dependencies["validate"]) == {
        "ingest-faceolat",
        "ingest-ava256",
        "ingest-stereo-rig",
        "ingest-nersemble",
    }
    decisions = plan(demo)
    assert decisions[0].reason == "output missing" and all(d.run for d in decisions)


def test_dry_run_of_the_real_template_names_missing_downloads(tmp_path):
    real = Path(__file__).resolve().parents[1] / "pipelines" / "real.yaml"
    (tmp_path / "data" / "ava256").mkdir(parents=True)
    (tmp_path / "data" / "vhap" / "ava256").mkdir(parents=True)
    (tmp_path / "data" / "vhap" / "template.obj").write_text("")
    (tmp_path / "data" / "splits").mkdir()
    (tmp_path / "data" / "splits" / "ava256.json").write_text("{}")
    result = CliRunner().invoke(
        run_command,
        [str(real), "--dry-run", "--var", f"data={tmp_path / 'data'}", "--var", f"out={tmp_path / 'out'}"],
    )
    assert result.exit_code == 1
    lines = {
        line.split()[1]: line for line in result.output.splitlines() if line[:4] in ("run ", "stop", "skip")
    }
    assert (
        lines["ingest-faceolat"].startswith("stop")
        and f"{tmp_path}/data/faceolat does not exist" in lines["ingest-faceolat"]
    )
    assert lines["ingest-ava256"].startswith("run ") and "output missing" in lines["ingest-ava256"]
    assert "would stop the run" in result.output
