"""Colour alignment of uncalibrated datasets (RelightAnyone §4.1).

A warm-up run trains stage 1 without lighting codes while learning one 3×3 ``C_d`` per uncalibrated
dataset ``d``, applied to the render: ``dataset_rgb ≈ C_d @ shared_rgb``. Its inverse maps the dataset's
colours into the shared space; it is stored beside the dataset's manifest with
:func:`relightanyone.format.colour_alignment.write_learned_colour_matrix` (``aligned = M @ rgb``), the loader applies
it, and the main run then trains with lighting codes on the aligned colours.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from relightanyone.align.colour import colour_matrix_problem
from relightanyone.errors import InputError
from relightanyone.format.colour_alignment import write_learned_colour_matrix
from relightanyone.format.dataset_view import link_dataset_view
from relightanyone.format.reader import load_manifest
from relightanyone.format.schema import COLOUR_ALIGNMENT_NAME
from relightanyone.model.networks.presets import Stage1Preset
from relightanyone.model.train.stage1 import Stage1Config, train_stage1

WARMUP_DIR = "warmup"
ALIGNMENT_REPORT = "colour_alignment.json"  # align-colour's report, beside the dataset views


def correction_from_render_matrix(render_to_dataset: np.ndarray) -> np.ndarray:
    """C (3, 3) mapping shared colour to the dataset's -> M = C⁻¹ mapping the dataset's colour to shared."""
    problem = colour_matrix_problem(render_to_dataset)
    if problem is not None:
        raise InputError(f"learned colour matrix: {problem}; train the warm-up longer")
    return np.linalg.inv(np.asarray(render_to_dataset, dtype=np.float64))


def colour_cast_error(render_to_dataset: np.ndarray, true_casts: list[np.ndarray]) -> dict[str, float]:
    """How close a learned ``C`` is to the true casts ``recorded = M_true @ true`` (one per camera).

    Returns the relative Frobenius error of C against the mean true cast, the same after removing a
    global gain (a 3×3 and an identity's albedo can trade a common exposure), and the largest
    off-identity entry of the residual cast ``C⁻¹ @ M_mean`` left after correction.
    """
    learned = np.asarray(render_to_dataset, dtype=np.float64)
    mean_cast = np.mean(np.stack([np.asarray(m, dtype=np.float64) for m in true_casts]), axis=0)
    relative = np.linalg.norm(learned - mean_cast) / np.linalg.norm(mean_cast)
    gain = float(np.sum(learned * mean_cast) / np.sum(learned * learned))
    relative_gain_free = np.linalg.norm(gain * learned - mean_cast) / np.linalg.norm(mean_cast)
    residual = np.linalg.inv(learned) @ mean_cast
    residual_normalised = residual / np.mean(np.diag(residual))
    return {
        "relative_error": float(relative),
        "relative_error_after_gain": float(relative_gain_free),
        "gain": gain,
        "residual_cast_max_offdiagonal_or_ratio": float(np.max(np.abs(residual_normalised - np.eye(3)))),
        "identity_baseline_relative_error": float(
            np.linalg.norm(np.eye(3) - mean_cast) / np.linalg.norm(mean_cast)
        ),
        "identity_baseline_residual": float(
            np.max(np.abs(mean_cast / np.mean(np.diag(mean_cast)) - np.eye(3)))
        ),
    }


def run_colour_warmup(
    data: list[Path],
    run_dir: Path,
    preset: Stage1Preset,
    uncalibrated: tuple[str, ...],
    seed: int = 0,
    progress: bool = True,
    eval_views_per_dataset: int | None = None,
    views_dir: Path | None = None,
    device: str = "auto",
) -> dict:
    """Warm-up into ``run_dir/warmup`` and store ``C⁻¹`` with each uncalibrated dataset.

    With ``views_dir`` the source datasets stay untouched: each uncalibrated dataset gets a view
    ``views_dir/<name>`` (:func:`relightanyone.format.dataset_view.link_dataset_view`) holding the matrix,
    and training reads that view instead. Returns the warm-up metrics (held-out PSNR/SSIM without and with the matrices, the matrices) on the
    main process, an empty dict elsewhere.
    """
    import torch.distributed as dist

    if not uncalibrated:
        raise InputError("the colour warm-up needs at least one uncalibrated dataset (--uncalibrated NAME)")
    warmup_preset = preset.replace(iterations=preset.warmup_iterations)
    config = Stage1Config(
        data=[Path(d) for d in data],
        out=Path(run_dir) / WARMUP_DIR,
        preset=warmup_preset,
        seed=seed,
        uncalibrated=tuple(uncalibrated),
        warmup=True,
        progress=progress,
        eval_views_per_dataset=eval_views_per_dataset,
        device=device,
    )
    metrics = train_stage1(config)
    is_main = not dist.is_initialized() or dist.get_rank() == 0
    if is_main:
        names = {load_manifest(Path(d)).info.name: Path(d) for d in data}
        for name, render_to_dataset in metrics["colour_matrices"].items():
            target = names[name]
            if views_dir is not None:
                target = link_dataset_view(
                    target, Path(views_dir) / name, exclude=frozenset({COLOUR_ALIGNMENT_NAME})
                )
            write_learned_colour_matrix(
                target,
                correction_from_render_matrix(np.asarray(render_to_dataset)),
                {
                    "method": "stage1 colour warm-up (RelightAnyone 4.1)",
                    "render_to_dataset": render_to_dataset,
                    "warmup_run": str(config.out.resolve()),
                    "iterations": warmup_preset.iterations,
                    "reference_datasets": sorted(set(names) - set(uncalibrated)),
                },
            )
    if dist.is_initialized():
        dist.barrier()  # the main run's loaders must see the matrices
    return metrics if is_main else {}


def align_colours(
    data: list[Path],
    uncalibrated: tuple[str, ...],
    preset: Stage1Preset,
    out: Path,
    seed: int = 0,
    eval_views_per_dataset: int | None = None,
    device: str = "auto",
) -> dict:
    """The colour warm-up into ``out`` with the sources untouched (what ``relightanyone align-colour`` does).

    Writes ``out/warmup/`` (the warm-up run), ``out/<dataset>/`` for every dataset in ``data`` (a view of
    it, carrying ``colour_alignment.json`` for the uncalibrated ones) and ``out/colour_alignment.json``,
    the report it returns: the datasets, the matrices and held-out PSNR/SSIM without and with them.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = {load_manifest(Path(d)).info.name: Path(d) for d in data}
    unknown = sorted(set(uncalibrated) - set(names))
    if unknown:
        raise InputError(f"--uncalibrated {unknown} is not among the --data datasets {sorted(names)}")
    metrics = run_colour_warmup(
        list(data),
        out,
        preset,
        tuple(uncalibrated),
        seed,
        eval_views_per_dataset=eval_views_per_dataset,
        views_dir=out,
        device=device,
    )
    for name, folder in names.items():
        if name not in uncalibrated:
            link_dataset_view(folder, out / name)
    report = {
        "uncalibrated": sorted(uncalibrated),
        "datasets": {name: str(folder) for name, folder in names.items()},
        **{k: v for k, v in metrics.items() if k != "losses"},
    }
    (out / ALIGNMENT_REPORT).write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    return report
