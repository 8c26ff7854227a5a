"""Choosing the single-stage baseline among its variants on validation subjects, never on test subjects.

The baseline has loss variants (``train stage2 --single-stage --single-stage-loss``) and a fair comparison
reports its better one. "Better" is decided here: each candidate run is fitted to every validation
subject of the OLAT dataset (split ``val`` in the world's splits or in the rows) with the evaluation's
fit settings, relit under the evaluated rig lights and scored against the subject's OLAT rows; the
candidate with the highest mean PSNR is the baseline of Table 1. Without validation subjects there is no
honest way to choose, so several candidates are refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from relightanyone.errors import InputError
from relightanyone.evaluation.truth import WorldAnswers
from relightanyone.format.torch_dataset import NormalizedTorchDataset
from relightanyone.model.train.run_files import read_run_info

VALIDATION_SPLIT = "val"


def validation_subjects(dataset_dir: Path, answers: WorldAnswers | None, world_name: str) -> list[str]:
    """Validation subjects of a dataset: the world's ``val`` split when it has one, else the rows'."""
    if answers is not None and world_name in answers.splits:
        names = sorted(s for s, split in answers.splits[world_name].items() if split == VALIDATION_SPLIT)
        if names:
            return names
    return sorted(set(NormalizedTorchDataset(dataset_dir, splits=VALIDATION_SPLIT).column("subject")))


def candidate_label(run: Path) -> str:
    """``<folder> (<loss variant>)`` of a single-stage run, from its run.json."""
    info = read_run_info(run)
    return f"{Path(run).name} ({info.get('single_stage_loss') or 'background'} loss)"


def choose_baseline(candidates: list[Path], scores: dict[str, list[float]]) -> tuple[Path, dict]:
    """The candidate with the highest mean validation PSNR, and the JSON-ready record of the choice.

    scores: str(candidate) -> per-image validation PSNR.
    """
    means = {str(c): float(np.mean(scores[str(c)])) for c in candidates}
    best = max(candidates, key=lambda c: means[str(c)])
    record = {
        "chosen": str(best),
        "on": "validation subjects (OLAT relighting PSNR)",
        "candidates": {
            str(c): {"label": candidate_label(c), "validation_psnr": means[str(c)]} for c in candidates
        },
    }
    return best, record


def require_validation(subjects: list[str], dataset_dir: Path, count: int) -> None:
    """Refuse to choose among ``count`` candidates without validation subjects."""
    if count > 1 and not subjects:
        raise InputError(
            f"{dataset_dir}: {count} single-stage runs were given but the dataset has no validation subjects "
            f"(split {VALIDATION_SPLIT!r}) to choose between them; give one --single-stage run or ingest with "
            "a validation split"
        )
