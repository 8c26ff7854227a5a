"""Memory estimates against memory measured on the CPU, the settings a plan proposes, and ``relightanyone plan``."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.model.networks.presets import get_preset, get_stage2_preset
from relightanyone.model.train.memory import (
    GIB,
    StepShape,
    estimate_stage1,
    estimate_stage2,
    measured_stage1,
    measured_stage2,
    planning_models,
    propose,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TOLERANCE = 0.25


@pytest.fixture(scope="module")
def models():
    """Stage 1 and stage 2 of the tiny presets at UV 64² on the planning template (4,096 Gaussians)."""
    torch.manual_seed(0)
    return planning_models(get_preset("tiny"), get_stage2_preset("tiny"))


def test_stage1_estimate_is_within_a_quarter_of_the_measured_peak(models):
    stage1, _ = models
    shape = StepShape(batch=4, crop=128)
    estimate = estimate_stage1(stage1, shape)["total"]
    measured = measured_stage1(stage1, shape)
    assert abs(estimate - measured) <= TOLERANCE * measured, (estimate / 2**20, measured / 2**20)


def test_stage2_estimate_is_within_a_quarter_of_the_measured_peak(models):
    stage1, stage2 = models
    shape = StepShape(batch=4, crop=128, lights=8)
    estimate = estimate_stage2(stage1, stage2, shape)["total"]
    measured = measured_stage2(stage1, stage2, shape)
    assert abs(estimate - measured) <= TOLERANCE * measured, (estimate / 2**20, measured / 2**20)


def test_bf16_and_checkpointing_lower_the_stage2_estimate(models):
    stage1, stage2 = models
    shape = StepShape(batch=4, crop=64, lights=8)
    plain = estimate_stage2(stage1, stage2, shape)
    lean = estimate_stage2(stage1, stage2, shape, "bf16", checkpointed=True)
    assert lean["activations"] < plain["activations"] and lean["recompute"] > 0
    assert plain["recompute"] == 0 and lean["total"] < plain["total"]


def test_propose_takes_the_largest_batch_that_fits_then_accumulates():
    def estimate(batch: int, precision: str, checkpointed: bool) -> dict[str, int]:
        per_sample = 10 if precision == "fp32" else 6
        per_sample -= 2 if checkpointed else 0
        return {"total": int(batch * per_sample * 1e9)}

    assert propose(estimate, 8, 80) == {
        "gpu_gb": 80,
        "batch": 8,
        "accumulation": 1,
        "precision": "bf16",
        "checkpointing": False,
        "estimated_gib": round(48e9 / GIB, 2),
    }
    on_48 = propose(estimate, 8, 48)
    assert (on_48["batch"], on_48["precision"], on_48["checkpointing"]) == (8, "bf16", True)
    without = propose(estimate, 8, 48, checkpointing=False)
    assert (without["batch"], without["accumulation"], without["precision"]) == (4, 2, "fp32")
    assert propose(estimate, 8, 4) is None


def test_plan_command_prints_and_writes_the_plan(tmp_path):
    out = tmp_path / "plan.json"
    result = CliRunner().invoke(cli, ["plan", "--preset", "tiny", "--lights", "4", "--json", str(out)])
    assert result.exit_code == 0, result.output
    plan = json.loads(out.read_text())
    assert plan["gaussians"] == 64 * 64 and plan["lights"] == 4
    for stage in ("stage1", "stage2", "single_stage", "fit"):
        assert plan["estimates_gib"][stage]["fp32"]["total"] > 0
    assert plan["proposals"]["stage2"]["24"]["batch"] == get_stage2_preset("tiny").batch_size
    assert "stage2 on 80 GB: batch 4 x 1 accumulation" in result.output
