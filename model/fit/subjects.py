"""Fitting the subjects of a normalized dataset into a folder of ``<subject>.avatar`` files and
``fit_report.json`` (what ``relightanyone fit`` writes)."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import check_name
from relightanyone.model.fit.fitter import FitSettings, fit_subject

FIT_REPORT_NAME = "fit_report.json"


@dataclass(frozen=True)
class SubjectFit:
    """One subject of a folder fit: its avatar file, whether it was ``kept`` from an earlier run (and not
    fitted again), and for a new fit its number of input ``views`` and final ``losses``."""

    subject: str
    avatar: Path
    kept: bool
    views: int = 0
    losses: dict[str, float] = field(default_factory=dict)


def subjects_to_fit(data: Path, subjects: Sequence[str], split: str, pattern: str) -> list[str]:
    """``subjects`` when given, else every subject of ``split`` with rows of lighting ``pattern``."""
    if subjects:
        return list(subjects)
    dataset = NormalizedDataset(data)
    chosen = sorted({key.split("/")[1] for key in dataset.select(splits=split, patterns=pattern)})
    if not chosen:
        raise InputError(
            f"{data}: no subject of split {split!r} has {pattern!r} rows; name subjects with --subject"
        )
    return chosen


def fit_subjects(
    stage1_run: Path,
    stage2_run: Path,
    data: Path,
    subjects: Sequence[str],
    out: Path,
    frame: int | None = None,
    cameras: list[str] | None = None,
    pattern: str = "full",
    settings: FitSettings | None = None,
    image_scale: float = 1.0,
    device: torch.device | str = "cpu",
    input_lighting: str = "rig",
) -> Iterator[SubjectFit]:
    """Fit each subject into ``out/<subject>.avatar`` (:func:`~relightanyone.model.fit.fitter.fit_subject`),
    yielding each as it is done; an avatar already in ``out`` is kept."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for subject in subjects:
        target = out / f"{check_name(subject, 'subject', str(data))}.avatar"
        if target.is_file():
            yield SubjectFit(subject, target, kept=True)
            continue
        avatar = fit_subject(
            stage1_run,
            stage2_run,
            data,
            subject,
            frame=frame,
            cameras=cameras,
            pattern=pattern,
            settings=settings,
            image_scale=image_scale,
            out=target,
            device=device,
            input_lighting=input_lighting,
        )
        views = len(avatar.metadata.get("cameras", []))
        yield SubjectFit(subject, target, False, views, dict(avatar.metadata.get("final_losses", {})))


def write_fit_report(out: Path, fits: Iterable[SubjectFit]) -> Path:
    """``out/fit_report.json``: avatar file, views and final losses of every subject fitted now, added to
    what the file held from earlier runs."""
    report = {
        fit.subject: {"avatar": fit.avatar.name, "views": fit.views, **fit.losses}
        for fit in fits
        if not fit.kept
    }
    path = Path(out) / FIT_REPORT_NAME
    if path.is_file():
        report = json.loads(path.read_text()) | report
    path.write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    return path
