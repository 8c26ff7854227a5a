"""Every computing stage on CUDA, on the sphere world: the trainers (stage 1, stage 2, single stage), a fit,
an expansion and an evaluation; and bf16 against fp32 on the GPU."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.sphere_world import build_sphere_world
from test_evaluate import write_sphere_answers
from test_precision import check_bf16_agrees_with_fp32, sphere  # noqa: F401 (sphere is a fixture)

from relightanyone.evaluation.run import run_evaluation
from relightanyone.evaluation.tables import EvaluationInputs, EvaluationSettings
from relightanyone.evaluation.truth import WorldAnswers
from relightanyone.format.validate import validate_path
from relightanyone.model.fit.fitter import FitSettings, fit_subject
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.run_files import CHECKPOINT_NAME, METRICS_NAME
from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The sphere world trained on CUDA: stage 1, stage 2 and the single-stage baseline (``--device`` is
    auto, which is CUDA here)."""
    torch.cuda.reset_peak_memory_stats()
    paths = build_sphere_world(tmp_path_factory.mktemp("gpu-world"), flat=True, single_stage=True)
    paths["peak_bytes"] = torch.cuda.max_memory_allocated()
    return paths


def test_every_trainer_steps_on_cuda(world):
    import json

    assert world["peak_bytes"] > 0  # the trainers allocated on the GPU
    for run in ("stage1", "stage2", "single_stage"):
        metrics = json.loads((world[run] / METRICS_NAME).read_text())
        assert metrics["iterations"] >= 1
        state = load_checkpoint(world[run] / CHECKPOINT_NAME)["model"]
        assert all(torch.isfinite(t).all() for t in state.values() if t.is_floating_point())


def test_fit_on_cuda(world, tmp_path):
    settings = FitSettings(inversion_iterations=3, finetune_iterations=2, progress=False)
    avatar = fit_subject(
        world["stage1"], world["stage2"], world["flat"], "f01", settings=settings, device="cuda"
    )
    assert avatar.means.is_cuda
    assert all(math.isfinite(v) for v in avatar.metadata["final_losses"].values())


def test_expansion_on_cuda(world, tmp_path):
    plan = plan_expansion(
        world["flat"], world["stage1"], world["stage2"], tmp_path, fit_iterations=(3, 2), device="cuda"
    )
    assert plan.settings.device.startswith("cuda")
    expand_dataset(plan, progress=False)
    assert [str(p) for p in validate_path(tmp_path / plan.info.name)] == []


def test_evaluation_on_cuda(world, tmp_path):
    answers = write_sphere_answers(tmp_path / "synthetic", world)
    inputs = EvaluationInputs(
        datasets={"d1": world["data"], "d2": world["flat"]},
        stage1=world["stage1"],
        stage2=world["stage2"],
        single_stage=world["single_stage"],
        answers=WorldAnswers(answers),
    )
    settings = EvaluationSettings(
        inversion_iterations=3, finetune_iterations=2, max_views=3, progress=False, device="cuda"
    )
    results = run_evaluation(inputs, settings, tmp_path / "out")
    assert (tmp_path / "out" / "report.md").is_file()
    assert results["settings"]["device"] == "cuda"


def test_bf16_agrees_with_fp32_on_cuda(sphere):  # noqa: F811
    check_bf16_agrees_with_fp32(sphere, "cuda")
