"""The shipped ``pipelines/real.yaml`` on a tiny synthetic world's native folders: it parses and plans with
``--var`` values pointing at them, and its dry run lists every stage with the training stages' memory."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers.small_worlds import make_world, reduced_preset

from relightanyone.pipelines.cli import run_command
from relightanyone.pipelines.dag.runner import load_pipeline, plan
from relightanyone.synth.presets import DatasetSize

REAL = Path(__file__).resolve().parents[1] / "pipelines" / "real.yaml"
NATIVE = {"faceolat": "d1", "ava256": "d2", "stereo_rig": "d3", "nersemble": "d4"}
MICRO = reduced_preset(
    template_segments=12,
    texture_size=8,
    answer_lights=2,
    d1=DatasetSize(train_subjects=2, test_subjects=1, cameras=2, image_size=(24, 32), lights=4),
    d2=DatasetSize(train_subjects=2, test_subjects=0, cameras=2, image_size=(42, 64), lights=4),
    d3=DatasetSize(train_subjects=2, test_subjects=0, cameras=8, image_size=(80, 60), lights=4),
    d4=DatasetSize(train_subjects=2, test_subjects=0, cameras=4, image_size=(48, 64), lights=8),
)


@pytest.fixture(scope="module")
def world_vars(tmp_path_factory) -> list[str]:
    """``--var`` arguments pointing real.yaml at a micro world's four native folders."""
    root = tmp_path_factory.mktemp("real-pipeline")
    world = make_world(root, MICRO, seed=2, datasets=tuple(NATIVE.values()))
    values = {
        "data": str(world),
        "splits": str(world / "splits"),
        "template": str(world / "tracking" / "template" / "template.obj"),
        "out": str(root / "out"),
        "preset": "tiny",
        "model_preset": "tiny",
        "workers": "1",
    }
    for name, code in NATIVE.items():
        values[f"{name}_tracking"] = str(world / "tracking" / code)
    return [f"{name}={value}" for name, value in values.items()]


def _overrides(world_vars: list[str]) -> dict[str, str]:
    return dict(v.split("=", 1) for v in world_vars)


def test_real_pipeline_plans_every_stage_from_ingest_to_report(world_vars):
    pipeline = load_pipeline(REAL, _overrides(world_vars))
    for stage in ("ingest-faceolat", "colour-align", "stage1", "stage2", "fit", "expand-ava256", "report"):
        assert stage in pipeline.order
    order = pipeline.order.index
    assert order("colour-align") < order("stage1") < order("stage2") < order("fit") < order("report")
    assert order("stage2") < order("expand-nersemble") < order("report")
    decisions = plan(pipeline)
    assert all(d.run and not d.reason.startswith("cannot run") for d in decisions), decisions
    assert {d.reason for d in decisions[:4]} == {"output missing"}  # the four ingests read the world


def test_dry_run_lists_every_stage_and_the_training_stages_memory(world_vars):
    arguments = [str(REAL), "--dry-run", *[a for v in world_vars for a in ("--var", v)]]
    arguments += ["--var", "gpus=2", "--var", "precision=bf16"]
    result = CliRunner().invoke(run_command, arguments)
    assert result.exit_code == 0, result.output
    names = load_pipeline(REAL, _overrides(world_vars)).order
    listed = [line.split()[1] for line in result.output.splitlines() if line.startswith("run ")]
    assert listed == names
    memory = [line.split("memory: ")[1] for line in result.output.splitlines() if "memory: " in line]
    assert len(memory) == 3, result.output  # colour-align (a stage-1 warm-up), stage 1, stage 2
    assert memory[0].startswith("stage1 step at preset tiny, batch 4, fp32: about")  # the warm-up is fp32
    assert memory[1].startswith("stage1 step at preset tiny, batch 4, bf16: about")
    assert memory[2].startswith("stage2 step at preset tiny, batch 4, bf16+checkpointing: about")
    assert all("GiB per GPU" in line for line in memory)
    assert f"{len(names)} of {len(names)} stage(s) would run" in result.output
