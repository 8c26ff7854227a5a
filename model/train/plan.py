"""Memory plans: what stage 1, stage 2 and a fit need per GPU at a preset, and settings that fit 24, 48
and 80 GB (what ``relightanyone plan`` prints). The estimates are :mod:`relightanyone.model.train.memory`'s."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from relightanyone.model.networks.gaussians import load_template_binding
from relightanyone.model.networks.presets import get_preset, get_stage2_preset
from relightanyone.model.networks.single_stage import SingleStageModel
from relightanyone.model.train.memory import (
    GIB,
    GPU_SIZES_GB,
    StepShape,
    estimate_fit,
    estimate_single_stage,
    estimate_stage1,
    estimate_stage2,
    planning_models,
    propose,
)

# Lights of the stage-2 rig assumed without a dataset: a light stage of this size (a full-on frame in a
# batch lights every light at once, so the batch carries them all).
DEFAULT_RIG_LIGHTS = 150
FIT_VIEWS = 4  # views per fitting step (``relightanyone fit --views-per-step``)
FIT_IMAGE = 512  # side of the fitted images


@dataclass(frozen=True)
class PlanRequest:
    """The run to plan: presets by name; batch and crop override the presets' (None: keep them)."""

    preset: str
    batch: int | None = None
    crop: int | None = None
    lights: int = DEFAULT_RIG_LIGHTS
    fit_views: int = FIT_VIEWS
    fit_image: int = FIT_IMAGE
    template: Path | None = None  # an OBJ with UVs; None: every texel a Gaussian (the upper bound)


def memory_plan(request: PlanRequest) -> dict:
    """Estimates (GiB by part) of stage 1, stage 2, the single-stage baseline and a fit, each at fp32 and,
    for the stage-2 networks, bf16 with checkpointing; and, per GPU size, the settings
    (:func:`~relightanyone.model.train.memory.propose`) that reach the preset's batch."""
    preset = get_preset(request.preset)
    stage2_preset = get_stage2_preset(request.preset)
    batch1 = request.batch or preset.batch_size
    batch2 = request.batch or stage2_preset.batch_size
    crop1 = request.crop or preset.crop_size
    crop2 = request.crop or stage2_preset.crop_size
    template = None if request.template is None else load_template_binding(request.template, preset.uv_size)
    stage1, stage2 = planning_models(preset, stage2_preset, template)
    single = SingleStageModel(
        preset, stage2_preset.sh_order, stage1.mesh_decoder.template_vertices, stage1.binding, 1
    )

    @functools.cache
    def stage1_at(batch: int, precision: str, checkpointed: bool) -> dict[str, int]:
        return estimate_stage1(stage1, StepShape(batch, crop1), precision)

    @functools.cache
    def stage2_at(batch: int, precision: str, checkpointed: bool) -> dict[str, int]:
        return estimate_stage2(
            stage1, stage2, StepShape(batch, crop2, request.lights), precision, checkpointed
        )

    @functools.cache
    def single_at(batch: int, precision: str, checkpointed: bool) -> dict[str, int]:
        return estimate_single_stage(single, StepShape(batch, crop2, request.lights), precision)

    fit_shape = StepShape(1, request.fit_image, request.lights, request.fit_views)
    estimates = {
        "stage1": {"fp32": stage1_at(batch1, "fp32", False), "bf16": stage1_at(batch1, "bf16", False)},
        "stage2": {
            "fp32": stage2_at(batch2, "fp32", False),
            "bf16+checkpointing": stage2_at(batch2, "bf16", True),
        },
        "single_stage": {
            "fp32": single_at(batch2, "fp32", False),
            "bf16": single_at(batch2, "bf16", False),
        },
        "fit": {
            "fp32": estimate_fit(stage1, stage2, fit_shape),
            "bf16": estimate_fit(stage1, stage2, fit_shape, "bf16"),
        },
    }
    proposals = {
        "stage1": {gb: propose(stage1_at, batch1, gb, checkpointing=False) for gb in GPU_SIZES_GB},
        "stage2": {gb: propose(stage2_at, batch2, gb) for gb in GPU_SIZES_GB},
        "single_stage": {gb: propose(single_at, batch2, gb, checkpointing=False) for gb in GPU_SIZES_GB},
    }
    return {
        "preset": request.preset,
        "gaussians": stage1.gaussian_count,
        "batch": {"stage1": batch1, "stage2": batch2},
        "crop": {"stage1": crop1, "stage2": crop2},
        "lights": request.lights,
        "fit": {"views": request.fit_views, "image": request.fit_image},
        "template": str(request.template) if request.template else "every texel (upper bound)",
        "estimates_gib": {
            stage: {
                setting: {k: round(v / GIB, 3) for k, v in parts.items()}
                for setting, parts in settings.items()
            }
            for stage, settings in estimates.items()
        },
        "proposals": proposals,
    }


def format_plan(plan: dict) -> str:
    """The plan as a few readable lines."""
    lines = [
        f"memory plan, preset {plan['preset']}: {plan['gaussians']:,} Gaussians ({plan['template']}), "
        f"batch {plan['batch']['stage1']} / {plan['batch']['stage2']} (stage 1 / 2), crop "
        f"{plan['crop']['stage1']} / {plan['crop']['stage2']}, {plan['lights']} lights",
        "estimated peak per GPU (GiB): "
        + "; ".join(
            f"{stage} " + ", ".join(f"{setting} {parts['total']:.1f}" for setting, parts in settings.items())
            for stage, settings in plan["estimates_gib"].items()
        ),
    ]
    for stage, by_gpu in plan["proposals"].items():
        for gb, choice in by_gpu.items():
            if choice is None:
                lines.append(f"  {stage} on {gb} GB: does not fit even at batch 1")
            else:
                lines.append(
                    f"  {stage} on {gb} GB: batch {choice['batch']} x {choice['accumulation']} accumulation, "
                    f"{choice['precision']}{', checkpointing' if choice['checkpointing'] else ''} "
                    f"({choice['estimated_gib']:.1f} GiB)"
                )
    return "\n".join(lines)
