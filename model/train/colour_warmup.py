"""Colour alignment of uncalibrated datasets (RelightAnyone §4.1), camera by camera.

A warm-up run trains stage 1 without lighting codes while learning one 3×3 ``C_d`` per uncalibrated
dataset ``d``, applied to the render: ``dataset_rgb ≈ C_d @ shared_rgb``. The cameras of an uncalibrated
rig also differ from each other (each sensor and filter has its own response), which one matrix per
dataset cannot undo; so, after the warm-up, each camera ``c`` of such a dataset gets its own
``C_c = diag(g_c) @ C_d``, with per-channel gains ``g_c`` from the warm-up's renders of its training views
against their images (the same heads seen by every camera pin the differences between cameras down).
Gains, not a free 3×3: skin colours lie close to one line in RGB, so a 3×3 per camera is not identifiable
from faces (an unconstrained fit on the reference world gave diagonal entries from −2 to 4). The inverses
map each camera's colours into the shared space; they are stored beside the dataset's manifest with
:func:`relightanyone.format.colour_alignment.write_learned_colour_matrix` (``aligned = M @ rgb``), the loader
applies the row's camera's matrix, and the main run then trains with lighting codes on the aligned colours.
A camera with too little subject in its training views keeps the dataset's matrix.
"""

from __future__ import annotations

import json
from collections.abc import Collection
from pathlib import Path

import numpy as np
import torch

from relightanyone.align.colour import colour_matrix_problem
from relightanyone.errors import InputError
from relightanyone.format.colour_alignment import write_learned_colour_matrix
from relightanyone.format.dataset_view import link_dataset_view
from relightanyone.format.reader import load_manifest
from relightanyone.format.schema import COLOUR_ALIGNMENT_NAME
from relightanyone.model.device import resolve_device
from relightanyone.model.metrics import interior_mask
from relightanyone.model.networks.presets import Stage1Preset
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.data import Stage1Data, ViewRef
from relightanyone.model.train.held_out import render_view
from relightanyone.model.train.run_files import CHECKPOINT_NAME
from relightanyone.model.train.sampling import evenly_spread
from relightanyone.model.train.stage1 import Stage1Config, build_model, train_stage1

WARMUP_DIR = "warmup"
ALIGNMENT_REPORT = "colour_alignment.json"  # align-colour's report, beside the dataset views
CAMERA_FIT_VIEWS = 16  # training views per camera rendered for its gains, spread over the subjects
MIN_CAMERA_PIXELS = 500  # interior subject pixels a camera needs for gains of its own


def camera_gains(render: np.ndarray, image: np.ndarray) -> np.ndarray:
    """(3,) per-channel gains g with ``image ≈ g * render``: the ratio of the channels' sums.

    render, image: (N, 3) linear RGB of the same pixels. A ratio of sums is unmoved by render error that
    averages out, where a least-squares fit is pulled toward zero by it (regression dilution).
    """
    return np.asarray(image, dtype=np.float64).sum(axis=0) / np.asarray(render, dtype=np.float64).sum(axis=0)


@torch.no_grad()
def fit_camera_matrices(
    config: Stage1Config, render_to_dataset: dict[str, list], datasets: Collection[str]
) -> dict[str, dict[str, np.ndarray]]:
    """The cameras' ``C_c = diag(g_c) @ C_d`` (render -> camera, 3×3) of each of ``datasets`` (uncalibrated
    ones), from the warm-up run of ``config`` and its dataset matrices ``render_to_dataset`` (``C_d``):
    {dataset: {camera: C_c}}. ``g_c`` are the camera's :func:`camera_gains` over the interior subject pixels
    of its training views. Cameras with fewer than :data:`MIN_CAMERA_PIXELS` such pixels, or a gain that is
    not positive, are left out (they keep the dataset's)."""
    data = Stage1Data(config.data, config.preset.held_out_cameras, apply_learned_colour=False)
    device = resolve_device(config.device)
    model = build_model(config.preset, data, config.uncalibrated, data.template_path).to(device)
    model.load_state_dict(load_checkpoint(Path(config.out) / CHECKPOINT_NAME)["model"])
    model.eval()
    fitted: dict[str, dict[str, np.ndarray]] = {}
    for index, name in enumerate(data.names):
        if name not in datasets:
            continue
        by_camera: dict[str, list[ViewRef]] = {}
        for view in data.train_views[index]:
            by_camera.setdefault(view.camera, []).append(view)
        dataset_matrix = np.asarray(render_to_dataset[name], dtype=np.float64)
        fitted[name] = {}
        for camera in sorted(by_camera):
            renders, images = [], []
            for view in evenly_spread(by_camera[camera], CAMERA_FIT_VIEWS):
                out = render_view(model, data, view, use_lighting=False)
                inside = interior_mask(out["mask"])[0, 0].numpy() > 0.5
                renders.append(out["render"][0].numpy()[:, inside].T)
                images.append(out["image"][0].numpy()[:, inside].T)
            render, image = np.concatenate(renders), np.concatenate(images)
            if len(render) < MIN_CAMERA_PIXELS:
                continue
            gains = camera_gains(render @ dataset_matrix.T, image)
            if np.all(np.isfinite(gains)) and np.all(gains > 0):
                fitted[name][camera] = np.diag(gains) @ dataset_matrix
    return fitted


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
    per_camera: Collection[str] | None = None,
) -> dict:
    """Warm-up into ``run_dir/warmup`` and store ``C⁻¹`` with each uncalibrated dataset, and each camera's
    ``C_c⁻¹`` with those of ``per_camera`` (None: every uncalibrated dataset; empty: none).

    With ``views_dir`` the source datasets stay untouched: each uncalibrated dataset gets a view
    ``views_dir/<name>`` (:func:`relightanyone.format.dataset_view.link_dataset_view`) holding the matrix,
    and training reads that view instead. Returns the warm-up metrics (held-out PSNR/SSIM without and with
    the dataset matrices, the matrices, the per-camera ones) on the main process, an empty dict elsewhere.
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
    per_camera = set(uncalibrated if per_camera is None else per_camera)
    if not per_camera <= set(uncalibrated):
        raise InputError(
            f"--per-camera {sorted(per_camera - set(uncalibrated))}: only --uncalibrated datasets get "
            "per-camera matrices"
        )
    metrics = train_stage1(config)
    is_main = not dist.is_initialized() or dist.get_rank() == 0
    if is_main:
        names = {load_manifest(Path(d)).info.name: Path(d) for d in data}
        fitted = fit_camera_matrices(config, metrics["colour_matrices"], per_camera) if per_camera else {}
        metrics["camera_matrices"] = {
            name: {camera: m.tolist() for camera, m in cameras.items()} for name, cameras in fitted.items()
        }
        for name, render_to_dataset in metrics["colour_matrices"].items():
            target = names[name]
            if views_dir is not None:
                target = link_dataset_view(
                    target, Path(views_dir) / name, exclude=frozenset({COLOUR_ALIGNMENT_NAME})
                )
            cameras = fitted.get(name, {})
            write_learned_colour_matrix(
                target,
                correction_from_render_matrix(np.asarray(render_to_dataset)),
                {
                    "method": "stage1 colour warm-up (RelightAnyone 4.1)"
                    + (", then per-channel gains per camera from its training views" if cameras else ""),
                    "render_to_dataset": render_to_dataset,
                    "warmup_run": str(config.out.resolve()),
                    "iterations": warmup_preset.iterations,
                    "reference_datasets": sorted(set(names) - set(uncalibrated)),
                    "camera_fit": {
                        "views_per_camera": CAMERA_FIT_VIEWS,
                        "min_pixels": MIN_CAMERA_PIXELS,
                        "model": "render_to_camera = diag(gains) @ render_to_dataset",
                        "cameras_fitted": len(cameras),
                    }
                    if name in per_camera
                    else None,
                },
                cameras={camera: correction_from_render_matrix(m) for camera, m in cameras.items()},
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
    per_camera: Collection[str] | None = None,
) -> dict:
    """The colour warm-up into ``out`` with the sources untouched (what ``relightanyone align-colour`` does);
    ``per_camera`` as :func:`run_colour_warmup`'s.

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
        per_camera=per_camera,
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
