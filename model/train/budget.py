"""The training budget of a run: how many views it trained on, read from its ``run.json``.

A budget is ``iterations × views per iteration × processes``. Comparisons between models are fair only at
equal budgets, so the single-stage baseline can be given the total of a two-stage model's runs
(:func:`matched_iterations`) and the evaluation reports every model's budget beside its numbers.
"""

from __future__ import annotations

import math
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.model.train.run_files import RUN_INFO_NAME, read_run_info


def run_budget(run: Path) -> dict:
    """Training budget of a run folder: {stage, iterations, batch_size, processes, samples}.

    samples = iterations × batch_size × processes: the views the run trained on.
    """
    path = Path(run) / RUN_INFO_NAME
    info = read_run_info(run)
    try:
        iterations = int(info["preset"]["iterations"])
        batch_size = int(info["preset"]["batch_size"])
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"{path}: the run's preset lacks iterations or batch_size ({error})") from error
    processes = int(info.get("processes", 1))
    return {
        "stage": info.get("stage"),
        "iterations": iterations,
        "batch_size": batch_size,
        "processes": processes,
        "samples": iterations * batch_size * processes,
    }


def two_stage_budget(stage1: Path, stage2: Path) -> dict:
    """Budget of a stage-1 run plus the stage-2 run on it: each run's budget and the total samples."""
    first, second = run_budget(stage1), run_budget(stage2)
    return {"stage1": first, "stage2": second, "samples": first["samples"] + second["samples"]}


def matched_iterations(samples: int, batch_size: int) -> int:
    """Iterations of ``batch_size`` views that train at least ``samples`` views."""
    if batch_size < 1:
        raise InputError(f"batch size must be >= 1, got {batch_size}")
    return max(1, math.ceil(samples / batch_size))
