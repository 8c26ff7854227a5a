"""One evaluation end to end: which world dataset each normalized dataset came from, every table, and the
written report (``report.md``, ``evaluation.json``, ``grids/``)."""

from __future__ import annotations

import shutil
from dataclasses import asdict
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.evaluation.report import write_report
from relightanyone.evaluation.tables import Evaluation, EvaluationInputs, EvaluationSettings
from relightanyone.evaluation.truth import WorldAnswers, match_world_dataset
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import MANIFEST_NAME


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


def run_evaluation(
    inputs: EvaluationInputs, settings: EvaluationSettings, out: Path, json_copy: Path | None = None
) -> dict:
    """Run every table, write ``out/report.md``, ``out/evaluation.json``, ``out/grids/``; returns results."""
    evaluation = Evaluation(inputs, settings)
    results = evaluation.run()
    results["settings"] = asdict(settings)
    inputs = evaluation.inputs  # the single-stage run chosen on validation subjects, when there was a choice
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
