"""Peak-memory estimates of a pipeline's training stages, for ``relightanyone run --dry-run``.

A stage trains when its command is ``relightanyone train stage1`` / ``train stage2`` (with or without
``--single-stage``) or ``align-colour`` (a stage-1 warm-up), run directly or through ``torchrun`` /
``python -m relightanyone``. Its estimate is :func:`relightanyone.model.train.plan.memory_plan`'s (what
``relightanyone plan`` prints) at the stage's ``--preset``, ``--batch-size`` and ``--precision``.
"""

from __future__ import annotations

import functools

from relightanyone.model.train.plan import PlanRequest, memory_plan
from relightanyone.pipelines.dag.pipeline_file import StageSpec

DEFAULT_MODEL_PRESET = "tiny"  # the trainers' --preset default
DEFAULT_PRECISION = "fp32"


def relightanyone_args(stage: StageSpec) -> list[str] | None:
    """The arguments after ``relightanyone`` of a stage that runs it (``run:``, ``-m relightanyone`` or the
    ``relightanyone`` executable in a ``command:``); None for any other command."""
    if stage.kind == "run":
        return list(stage.args)
    args = list(stage.args)
    for index, arg in enumerate(args):
        if arg == "relightanyone" and index > 0 and args[index - 1] == "-m":
            return args[index + 1 :]
        if arg.rsplit("/", 1)[-1] == "relightanyone":
            return args[index + 1 :]
    return None


def option_value(args: list[str], name: str, default: str) -> str:
    """The value of ``--name VALUE`` or ``--name=VALUE`` in ``args`` (the last one given), else ``default``."""
    value = default
    for index, arg in enumerate(args):
        if arg == name and index + 1 < len(args):
            value = args[index + 1]
        elif arg.startswith(f"{name}="):
            value = arg.split("=", 1)[1]
    return value


def trained_model(args: list[str]) -> str | None:
    """Which estimate of :func:`memory_plan` a command's step is: stage1, stage2, single_stage or None."""
    if args[:1] == ["align-colour"] or args[:2] == ["train", "stage1"]:
        return "stage1"
    if args[:2] == ["train", "stage2"]:
        return "single_stage" if "--single-stage" in args else "stage2"
    return None


@functools.cache
def _plan(preset: str, batch: int | None) -> dict:
    return memory_plan(PlanRequest(preset, batch))


def stage_memory(stage: StageSpec) -> str | None:
    """One line: the estimated peak memory per GPU of a training stage's step, None for a stage
    that does not train."""
    args = relightanyone_args(stage)
    model = trained_model(args) if args else None
    if model is None:
        return None
    preset = option_value(args, "--preset", DEFAULT_MODEL_PRESET)
    precision = option_value(args, "--precision", DEFAULT_PRECISION)
    batch = option_value(args, "--batch-size", "")
    plan = _plan(preset, int(batch) if batch.isdigit() else None)
    settings = plan["estimates_gib"][model]
    # The plan's bf16 stage-2 estimate has checkpointed maps; fp32 ones have none (an upper bound).
    setting = "bf16+checkpointing" if model == "stage2" and precision == "bf16" else precision
    if setting not in settings:
        setting = DEFAULT_PRECISION
    total = settings[setting]["total"]
    per_gpu_batch = plan["batch"]["stage1" if model == "stage1" else "stage2"]
    return (
        f"{model} step at preset {preset}, batch {per_gpu_batch}, {setting}: about "
        f"{total:.2f} GiB per GPU (relightanyone plan --preset {preset})"
    )
