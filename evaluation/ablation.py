"""The lighting-code ablation (paper's z_l ablation) and the training budget of every compared model.

Three *arms* are trained on the same data with the same budget and compared on the same flat-lit subjects:

* ``with-zl``: stage 1 with a lighting code per dataset, stage 2 on top (the method),
* ``no-zl``: stage 1 trained without lighting codes (``train stage1 --no-lighting-code``), its own stage 2,
* ``colour-matrix``: no lighting codes either, but every flat-lit dataset aligned to the OLAT dataset by a
  learned 3×3 colour matrix first (``align-colour`` with every flat dataset ``--uncalibrated``).

An arm is a stage-1 run and the stage-2 run trained on it; its budget is read from the runs
(:mod:`relightanyone.model.train.budget`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.model.fit.fitter import RelightableModel, load_relightable_model
from relightanyone.model.train.budget import run_budget, two_stage_budget
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.run_files import CHECKPOINT_NAME, read_run_info

# Command-line arm name -> the row it fills in the ablation tables.
ARM_ROWS = {
    "with-zl": "with_lighting_code",
    "no-zl": "without_lighting_code",
    "colour-matrix": "colour_matrix",
}


def single_run_budget(run: Path) -> dict:
    """Budget of one run (the single-stage baseline), in the shape of :func:`two_stage_budget`."""
    budget = run_budget(run)
    return {"single_stage": budget, "samples": budget["samples"]}


def budget_text(budget: dict | None) -> str:
    """One line for the report, e.g. ``10,400 views (stage 1: 2000 × 4; stage 2: 600 × 4)``."""
    if not budget:
        return "–"
    parts = [
        f"{name.replace('_', '-').replace('stage', 'stage ')}: {part['iterations']} × {part['batch_size']}"
        + (f" × {part['processes']} processes" if part["processes"] > 1 else "")
        for name, part in budget.items()
        if isinstance(part, dict)
    ]
    return f"{budget['samples']:,} views ({'; '.join(parts)})"


@dataclass
class AblationArm:
    """One arm: the row it fills, its relightable model, its stage-1 subjects and its budget."""

    row: str
    model: RelightableModel
    subjects: list[str]
    budget: dict
    lighting_code: bool
    runs: tuple[str, str]
    datasets: dict[str, Path]  # dataset name -> the folder its stage 1 trained on (its colour alignment)


def stage1_datasets(stage1: Path) -> dict[str, Path]:
    """Dataset name -> folder of every dataset a stage-1 run trained on (from its run.json)."""
    info = read_run_info(stage1)
    return {entry["name"]: Path(entry["path"]) for entry in info.get("datasets", [])}


def arm_subject_index(arm: AblationArm, dataset: str, subject: str) -> int:
    """Identity-code row of ``dataset/subject`` in the arm's stage 1 (refused when it never trained on it)."""
    name = f"{dataset}/{subject}"
    if name not in arm.subjects:
        raise InputError(
            f"{arm.runs[0]}: ablation arm {arm.row!r} did not train on {name!r}; train every arm on the same data"
        )
    return arm.subjects.index(name)


def arm_dataset(arm: AblationArm, dataset: str, fallback: Path) -> Path:
    """The folder the arm's stage 1 read ``dataset`` from (its own colour alignment), else ``fallback``."""
    path = arm.datasets.get(dataset)
    return path if path is not None and path.is_dir() else Path(fallback)


def load_arm(name: str, stage1: Path, stage2: Path, device: str = "cpu") -> AblationArm:
    """Load arm ``name`` (a key of :data:`ARM_ROWS`) from its stage-1 and stage-2 runs.

    Refuses an arm whose stage 1 disagrees with its name (``with-zl`` trained without lighting codes or
    the other way round), so the table cannot mislabel what it compares.
    """
    if name not in ARM_ROWS:
        raise InputError(f"unknown ablation arm {name!r}; expected one of {', '.join(ARM_ROWS)}")
    checkpoint = load_checkpoint(Path(stage1) / CHECKPOINT_NAME)
    lighting_code = bool(checkpoint.get("lighting_code", True))
    if lighting_code != (name == "with-zl"):
        raise InputError(
            f"{stage1}: ablation arm {name!r} needs a stage 1 trained "
            f"{'with' if name == 'with-zl' else 'without'} lighting codes "
            f"(train stage1 {'' if name == 'with-zl' else '--no-lighting-code'})".rstrip()
            + f"; this one was trained {'with' if lighting_code else 'without'}"
        )
    return AblationArm(
        row=ARM_ROWS[name],
        model=load_relightable_model(stage1, stage2, device),
        subjects=list(checkpoint["subjects"]),
        budget=two_stage_budget(stage1, stage2),
        lighting_code=lighting_code,
        runs=(str(stage1), str(stage2)),
        datasets=stage1_datasets(stage1),
    )


def load_arms(
    arms: dict[str, tuple[Path, Path]],
    main: RelightableModel,
    stage1: Path,
    stage2: Path,
    device: str = "cpu",
) -> dict[str, AblationArm]:
    """Every given arm (loaded on ``device``), keyed by its row; without a ``with-zl`` arm the main runs are
    that arm."""
    loaded = {ARM_ROWS[name]: load_arm(name, *runs, device) for name, runs in arms.items()}
    if ARM_ROWS["with-zl"] not in loaded:
        loaded = {
            ARM_ROWS["with-zl"]: AblationArm(
                row=ARM_ROWS["with-zl"],
                model=main,
                subjects=list(load_checkpoint(Path(stage1) / CHECKPOINT_NAME)["subjects"]),
                budget=two_stage_budget(stage1, stage2),
                lighting_code=True,
                runs=(str(stage1), str(stage2)),
                datasets=stage1_datasets(stage1),
            ),
            **loaded,
        }
    return loaded


def budgets_agree(arms: dict[str, AblationArm]) -> bool:
    """Whether every arm trained the same number of views in stage 1 and in stage 2."""
    shapes = {(a.budget["stage1"]["samples"], a.budget["stage2"]["samples"]) for a in arms.values()}
    return len(shapes) == 1
