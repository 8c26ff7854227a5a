"""Splits: a published protocol reaches every row, training reads only training subjects, the demo
pipeline ingests with the world's protocol, and an evaluation of held-out subjects refuses any subject a
run trained on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers.custom_capture import make_capture

from relightanyone.cli import cli
from relightanyone.errors import InputError
from relightanyone.evaluation.splits import (
    TrainingRun,
    recorded_views,
    refuse_trained_subjects,
    training_run,
)
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest.records import published_splits
from relightanyone.model.train.data import Stage1Data
from relightanyone.model.train.run_files import RUN_INFO_NAME, read_run_info
from relightanyone.pipelines.dag.pipeline_file import parse_pipeline

REPO = Path(__file__).resolve().parents[1]
PROTOCOL = {"s1": "train", "s2": "val", "s3": "test"}


@pytest.fixture(scope="module")
def split_dataset(tmp_path_factory) -> Path:
    """A custom capture of three subjects ingested with a protocol: s1 train, s2 val, s3 test."""
    root = tmp_path_factory.mktemp("splits")
    capture = make_capture(root / "capture", subjects=tuple(PROTOCOL), frames=(0,))
    protocol = root / "splits.json"
    protocol.write_text(json.dumps({"s2": "val", "s3": "test"}))  # s1 unlisted: train
    result = CliRunner().invoke(
        cli,
        ["ingest", "custom", str(capture), "--splits", str(protocol), "--out", str(root / "out")]
        + ["--preset", "tiny", "--workers", "1"],
    )
    assert result.exit_code == 0, result.output
    return root / "out" / "custom"


def test_published_splits_reach_the_rows_and_only_train_rows_train(split_dataset):
    dataset = NormalizedDataset(split_dataset)
    for subject, split in PROTOCOL.items():
        keys = dataset.select(subjects=subject)
        assert keys and set(dataset.select(subjects=subject, splits=split)) == set(keys), subject
    data = Stage1Data([split_dataset], held_out_per_subject=0)
    assert data.subjects == ["custom/s1"]
    assert {v.subject for views in data.train_views for v in views} == {"s1"}


def test_a_protocol_with_an_unknown_split_is_refused(tmp_path):
    protocol = tmp_path / "splits.json"
    protocol.write_text(json.dumps({"s1": "train", "s2": "holdout"}))
    with pytest.raises(InputError, match="split values must be one of train, val, test"):
        published_splits(protocol)


def test_the_demo_pipeline_ingests_every_dataset_with_the_worlds_protocol():
    """Rows get the world's splits at ingest, so the trainers (which read split 'train') never see a
    validation or test subject, and the expansion expands training subjects only."""
    pipeline = parse_pipeline(REPO / "pipelines" / "demo.yaml", {"out": "/tmp/demo-splits"})
    stages = {stage.name: stage for stage in pipeline.stages}
    world = stages["world"].output
    ingests = [s for s in pipeline.stages if s.args[0] == "ingest"]
    assert len(ingests) == 4
    for stage in ingests:
        protocol = Path(stage.args[stage.args.index("--splits") + 1])
        assert protocol.parent == world / "splits" and protocol.name == f"{Path(stage.args[2]).name}.json"
    for stage in pipeline.stages:
        if stage.args[0] == "expand":
            assert stage.args[stage.args.index("--splits") + 1] == "train", stage.name
        if stage.args[0] in ("fit", "evaluate") and "--split" in stage.args:
            assert stage.args[stage.args.index("--split") + 1] == "test", stage.name


def test_the_reference_baseline_trains_the_two_stage_budget_with_both_losses():
    """`make reference` gives the single-stage baseline the two-stage model's whole budget, once per
    loss, and the evaluation chooses between the two on validation subjects."""
    assert "--var single_stage_share=1" in (REPO / "Makefile").read_text()
    pipeline = parse_pipeline(
        REPO / "pipelines" / "demo.yaml", {"out": "/tmp/ref", "single_stage_share": "1"}
    )
    stages = {stage.name: stage for stage in pipeline.stages}
    runs = {name: stages[name].output for name in ("stage1", "stage2", "single-stage", "single-stage-masked")}
    losses = set()
    for name in ("single-stage", "single-stage-masked"):
        args = stages[name].args
        match = args.index("--match-budget")
        assert list(args[match + 1 : match + 3]) == [str(runs["stage1"]), str(runs["stage2"])], name
        assert args[args.index("--match-share") + 1] == "1" and "--iterations" not in args, name
        losses.add(args[args.index("--single-stage-loss") + 1])
    assert losses == {"background", "masked"}
    evaluate = stages["evaluate"].args
    candidates = [evaluate[i + 1] for i, arg in enumerate(evaluate) if arg == "--single-stage"]
    assert candidates == [str(runs["single-stage"]), str(runs["single-stage-masked"])]


def write_run(folder: Path, info: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / RUN_INFO_NAME).write_text(json.dumps(info))
    return folder


def test_recorded_views_of_old_and_new_runs(tmp_path):
    new = write_run(tmp_path / "new", {"stage": "stage1", "seed": 3, "trained_views": {"d/a": ["c0", "c1"]}})
    assert training_run("stage 1", new) == TrainingRun("stage 1", new, {"d/a": ["c0", "c1"]}, 3)
    # A stage-2 run without trained_views lists stage 1's codes but trains on its own dataset only.
    old = {"stage": "stage2", "dataset": {"name": "olat"}, "subjects": ["olat/a", "flat/b"]}
    assert recorded_views(old) == {"olat/a": []}
    with pytest.raises(InputError, match="nowhere/run.json: not a training run folder"):
        training_run("stage 2", tmp_path / "nowhere")


def test_a_held_out_subject_that_trained_is_refused_naming_it_and_the_run(tmp_path):
    run = TrainingRun("stage 1", tmp_path / "s1", {"custom/s3": ["c0"]})
    refuse_trained_subjects("test", ["custom/s2"], [run])  # never trained: fine
    with pytest.raises(InputError, match=r"test subject custom/s3 reached training in the stage 1 run"):
        refuse_trained_subjects("test", ["custom/s3"], [run])
    with pytest.raises(InputError, match="held-out splits are val, test"):
        refuse_trained_subjects("train", [], [run])


def test_evaluate_refuses_a_test_subject_a_run_trained_on(split_dataset, tmp_path):
    """Through the command: the runs' recorded inputs name the test subject, so nothing is fitted and the
    one-line error names the subject and the run."""
    world = tmp_path / "world"
    (world / "answers").mkdir(parents=True)
    (world / "answers" / "splits.json").write_text(json.dumps({"d1": PROTOCOL}))
    dataset = {"name": "custom", "path": str(split_dataset)}
    stage1 = write_run(
        tmp_path / "stage1",
        {
            "stage": "stage1",
            "datasets": [dataset],
            "trained_views": {"custom/s1": ["c0"], "custom/s3": ["c1"]},
        },
    )
    stage2 = write_run(
        tmp_path / "stage2", {"stage": "stage2", "dataset": dataset, "trained_views": {"custom/s1": ["c0"]}}
    )
    args = ["evaluate", "--world", str(world), "--data", f"d1={split_dataset}", "--stage1", str(stage1)]
    args += ["--stage2", str(stage2), "--out", str(tmp_path / "eval"), "--quiet"]
    result = CliRunner().invoke(cli, args)
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1, result.output
    assert "custom/s3" in lines[0] and str(stage1) in lines[0] and "stage 1 run" in lines[0]
    # The validation subject never trained, so model selection on it is allowed past the check (and then
    # fails later only because these runs have no checkpoint).
    result = CliRunner().invoke(cli, [*args, "--split", "val"])
    assert "reached training" not in result.output
    (world / "answers" / "splits.json").write_text(json.dumps({"d1": {"s1": "train", "s3": "test"}}))
    result = CliRunner().invoke(cli, [*args, "--split", "val"])
    assert result.exit_code == 1 and "no val subjects" in result.stderr, result.output


def test_the_colour_warmup_run_is_found_after_its_folder_moved(tmp_path):
    """A dataset view names its warm-up run by absolute path; a moved aligned/ folder is still checked
    (warmup/ beside the views), and a lost run is an error rather than an unchecked evaluation."""
    from relightanyone.evaluation.splits import warmup_runs

    aligned = tmp_path / "aligned"
    view = aligned / "ava256"
    view.mkdir(parents=True)
    document = {"info": {"warmup_run": str(tmp_path / "elsewhere" / "warmup")}}
    (view / "colour_alignment.json").write_text(json.dumps(document))
    with pytest.raises(InputError, match="colour warm-up run .* is gone"):
        warmup_runs([view])
    write_run(aligned / "warmup", {"stage": "stage1-warmup", "trained_views": {"ava256/a": ["c0"]}})
    assert warmup_runs([view, aligned / "faceolat"]) == [aligned / "warmup"]


def test_every_run_an_evaluation_uses_is_checked(tmp_path):
    """Stage 1, stage 2, further runs (ablation arms) and the warm-ups named by any of their datasets."""
    from relightanyone.evaluation.splits import training_runs

    view = tmp_path / "aligned-arm" / "flat"
    view.mkdir(parents=True)
    warmup = write_run(tmp_path / "aligned-arm" / "warmup", {"trained_views": {"flat/w": ["c0"]}})
    (view / "colour_alignment.json").write_text(json.dumps({"info": {"warmup_run": str(warmup)}}))
    stage1 = write_run(tmp_path / "s1", {"datasets": [], "trained_views": {"olat/a": ["c0"]}})
    stage2 = write_run(tmp_path / "s2", {"trained_views": {"olat/a": ["c0"]}})
    arm = write_run(
        tmp_path / "arm", {"datasets": [{"name": "flat", "path": str(view)}], "trained_views": {}}
    )
    runs = training_runs(stage1, stage2, None, [], {"no-zl stage 1": arm})
    assert [r.label for r in runs] == ["stage 1", "stage 2", "no-zl stage 1", "colour warm-up"]
    with pytest.raises(InputError, match="flat/w reached training in the colour warm-up run"):
        refuse_trained_subjects("test", ["flat/w"], runs)


def test_a_run_record_that_is_missing_damaged_or_of_another_stage_is_named(tmp_path):
    with pytest.raises(InputError, match="run.json: not a training run folder.*relightanyone train stage2"):
        read_run_info(tmp_path, "stage2")
    (tmp_path / "run.json").write_text('{"stage": "stage1"')
    with pytest.raises(InputError, match="run.json: not valid JSON"):
        read_run_info(tmp_path)
    (tmp_path / "run.json").write_text('{"stage": "stage1"}')
    with pytest.raises(InputError, match="field 'stage' is 'stage1', expected 'stage2'"):
        read_run_info(tmp_path, "stage2")
    assert read_run_info(tmp_path, "stage1") == {"stage": "stage1"}
