"""Which subjects reached training, and the refusal to score any of them as held out.

Every training run writes ``run.json`` with ``trained_views``: each ``<dataset>/<subject>`` whose rows it
trained on, with their cameras (:mod:`relightanyone.model.train.run_files`). The runs an evaluation
depends on are stage 1, stage 2, the single-stage baseline and the colour warm-up that learned a
dataset's colour matrix (named in the dataset view's ``colour_alignment.json``). A held-out subject
(split ``val`` or ``test``) that appears in any of them is refused before anything is fitted: its numbers
would measure memory, not generalization.

Runs written before ``trained_views`` existed are read from their ``subjects`` list (every identity
code; a stage-2 run lists stage 1's codes but trains on its own dataset only).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.format.schema import COLOUR_ALIGNMENT_NAME
from relightanyone.model.train.colour_warmup import WARMUP_DIR
from relightanyone.model.train.run_files import RUN_INFO_NAME, TRAINED_VIEWS_KEY, read_run_info

HELD_OUT_SPLITS = ("val", "test")
STAGE2_KINDS = ("stage2", "single-stage")


@dataclass(frozen=True)
class TrainingRun:
    """A run whose training data an evaluation depends on: its label, folder and recorded views."""

    label: str  # "stage 1", "stage 2", "single-stage", "colour warm-up"
    path: Path
    views: dict[str, list[str]]  # "<dataset>/<subject>" -> cameras whose rows reached training
    seed: int | None = None


def training_run(label: str, run_dir: Path) -> TrainingRun:
    """The run at ``run_dir`` with the views it trained on and its seed."""
    info = read_run_info(run_dir)
    return TrainingRun(label, Path(run_dir), recorded_views(info), info.get("seed"))


def recorded_views(info: dict) -> dict[str, list[str]]:
    """{``<dataset>/<subject>``: cameras} a run trained on, from its ``run.json`` document.

    A run without ``trained_views`` gives its ``subjects`` with an empty camera list (every view)."""
    if TRAINED_VIEWS_KEY in info:
        return {subject: list(cameras) for subject, cameras in info[TRAINED_VIEWS_KEY].items()}
    dataset = info.get("dataset", {}).get("name") if info.get("stage") in STAGE2_KINDS else None
    return {s: [] for s in info.get("subjects", []) if dataset is None or s.split("/", 1)[0] == dataset}


def warmup_runs(dataset_dirs: list[Path]) -> list[Path]:
    """Colour warm-up runs named by the datasets' ``colour_alignment.json`` (their learned matrices).

    A folder moved since (the recorded path has no ``run.json``) is looked for where ``align-colour``
    writes it, ``warmup/`` beside the dataset views."""
    runs = []
    for folder in dataset_dirs:
        path = Path(folder) / COLOUR_ALIGNMENT_NAME
        if not path.is_file():
            continue
        try:
            recorded = json.loads(path.read_text()).get("info", {}).get("warmup_run")
        except ValueError as error:
            raise InputError(f"{path}: not valid JSON ({error})") from None
        if not recorded:
            continue
        candidates = [Path(recorded), Path(folder).parent / WARMUP_DIR]
        run = next((c for c in candidates if (c / RUN_INFO_NAME).is_file()), None)
        if run is None:
            raise InputError(
                f"{path}: its colour warm-up run {recorded} is gone; the split check needs the subjects it "
                "trained on (restore the run folder or re-run align-colour)"
            )
        if run not in runs:
            runs.append(run)
    return runs


def training_runs(
    stage1: Path,
    stage2: Path,
    single_stage: Path | None,
    dataset_dirs: list[Path],
    other_runs: dict[str, Path] | None = None,
) -> list[TrainingRun]:
    """The runs an evaluation of these runs and datasets depends on, with what each trained on.

    other_runs: further labelled runs the evaluation uses (e.g. ablation arms). The colour warm-ups are
    those of the evaluated datasets and of the datasets every one of these runs trained on."""
    named = [("stage 1", stage1), ("stage 2", stage2), ("single-stage", single_stage)]
    named += list((other_runs or {}).items())
    runs = [training_run(label, path) for label, path in named if path is not None]
    trained_data = [
        Path(d["path"])
        for run in runs
        for d in read_run_info(run.path).get("datasets", [])
        if isinstance(d, dict) and "path" in d
    ]
    warmups = warmup_runs([*dataset_dirs, *trained_data])
    return runs + [training_run("colour warm-up", path) for path in warmups]


def runs_that_trained(subject_key: str, runs: list[TrainingRun]) -> list[TrainingRun]:
    """The runs whose training rows include ``<dataset>/<subject>``."""
    return [run for run in runs if subject_key in run.views]


def refuse_trained_subjects(split: str, subject_keys: list[str], runs: list[TrainingRun]) -> None:
    """Raise InputError naming the first held-out subject that reached a run's training, and the run."""
    if split not in HELD_OUT_SPLITS:
        raise InputError(f"evaluate --split {split!r}: held-out splits are {', '.join(HELD_OUT_SPLITS)}")
    for key in subject_keys:
        for run in runs_that_trained(key, runs):
            cameras = ", ".join(run.views[key]) or "all views"
            raise InputError(
                f"{run.path / RUN_INFO_NAME}: {split} subject {key} reached training in the {run.label} run "
                f"({cameras}); a {split} subject must never train: re-split the data or retrain without it"
            )
