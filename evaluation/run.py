"""One evaluation end to end: which world dataset each normalized dataset came from, every table, and the
written report (``report.md``, ``evaluation.json``, ``grids/``)."""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.evaluation.protocol import (
    PAPER_NUMBERS,
    add_statistics,
    held_out_counts,
    protocol_hash,
    protocol_record,
    run_kind,
)
from relightanyone.evaluation.report import write_report
from relightanyone.evaluation.tables import Evaluation, EvaluationInputs, EvaluationSettings
from relightanyone.evaluation.truth import WorldAnswers, match_world_dataset
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import MANIFEST_NAME
from relightanyone.model.train.run_files import METRICS_NAME


def world_datasets(values: tuple[str, ...], answers: WorldAnswers) -> dict[str, Path]:
    """``NAME=DIR`` (NAME = the world's dataset folder, d1..d4) or a bare ``DIR`` matched by its cameras
    -> {world dataset: normalized dataset folder}."""
    datasets: dict[str, Path] = {}
    for value in values:
        name, sep, folder = value.partition("=")
        path = Path(folder if sep else value)
        if not (path / MANIFEST_NAME).is_file():
            raise InputError(f"{path}: not a normalized dataset (no {MANIFEST_NAME})")
        if not sep:
            name = match_world_dataset(answers, set(NormalizedDataset(path).cameras), str(path))
        if name in datasets:
            raise InputError(f"world dataset {name!r} given twice (--data)")
        datasets[name] = path
    return datasets


def stage1_held_out(stage1: Path) -> dict | None:
    """Stage 1's held-out-view scores per dataset ({name: {psnr, ssim, views}}), None when not recorded."""
    path = Path(stage1) / METRICS_NAME
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text()).get("held_out")
    except ValueError as error:
        raise InputError(f"{path}: not valid JSON ({error})") from None


def run_evaluation(
    inputs: EvaluationInputs, settings: EvaluationSettings, out: Path, json_copy: Path | None = None
) -> dict:
    """Run every table, write ``out/report.md``, ``out/evaluation.json``, ``out/grids/``; returns results."""
    evaluation = Evaluation(inputs, settings)
    results = evaluation.run()
    results["settings"] = asdict(settings)
    results["protocol"] = protocol_record(settings, evaluation.fit_settings())
    results["protocol_sha256"] = protocol_hash(results["protocol"])
    add_statistics(results)
    results["held_out_subjects"] = held_out_counts(results)
    results["run_kind"] = run_kind(results)
    results["paper_numbers"] = PAPER_NUMBERS
    results["stage1_held_out"] = stage1_held_out(inputs.stage1)
    results["training_runs"] = [
        {"label": run.label, "path": str(run.path), "seed": run.seed} for run in evaluation.training_runs
    ]
    results["inputs"] = {
        "world": None if inputs.answers is None else str(inputs.answers.world),
        "datasets": {k: str(v) for k, v in inputs.datasets.items()},
        "stage1": str(inputs.stage1),
        "stage2": str(inputs.stage2),
        "single_stage": None if inputs.single_stage is None else str(inputs.single_stage),
    }
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_report(out, results, evaluation.tables, evaluation.inputs_images)
    if json_copy is not None:
        Path(json_copy).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "evaluation.json", json_copy)
    return results
