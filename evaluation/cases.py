"""Ground-truth cases of the evaluation: images under one lighting, in the model's image space.

A :class:`LightCase` is one lighting (an OLAT light, or an environment map as weights over the OLAT answer
lights) with the ground-truth views under it. Cases come from

* the normalized OLAT rows of a subject (:func:`row_olat_cases`; D1 test subjects have them),
* the world's answers (:func:`answer_olat_cases`, :func:`answer_envmap_cases`), warped into the crops of
  the subject's normalized rows (:mod:`relightanyone.evaluation.truth`),
* any function giving the true image of (camera, light) (:func:`callable_olat_cases`), for worlds whose
  truth is analytic.

Rows of normalized datasets are read through
:class:`~relightanyone.format.torch_dataset.NormalizedTorchDataset`, as training and fitting read them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.evaluation.truth import (
    NativeCamera,
    WorldAnswers,
    match_lights,
    read_answer_image,
    warp_native_to_row,
    world_to_normalized,
)
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.torch_dataset import LEARNED, NormalizedTorchDataset, image_hwc
from relightanyone.model.metrics import interior_mask
from relightanyone.render.camera import Cameras
from relightanyone.render.lights import PointLights

ANSWER_MASK_THRESHOLD = 1e-4  # linear radiance summed over the answer lights; the background is exactly 0


@dataclass
class EvalView:
    """One ground-truth image: pinhole K (3, 3), w2c (4, 4) normalized canonical, image (H, W, 3), mask (H, W)."""

    camera: str
    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    image: np.ndarray
    mask: np.ndarray


def item_view(item: dict) -> EvalView:
    """The :class:`EvalView` of a dataset item (its image, mask and camera)."""
    return EvalView(
        item["camera"],
        item["K"].numpy(),
        item["w2c"].numpy(),
        item["width"],
        item["height"],
        image_hwc(item),
        item["mask"][0].numpy(),
    )


@dataclass
class LightCase:
    """A lighting and its ground truth. OLAT: ``light`` (one point light). Env map: ``weights`` (L, 3) of
    the relit image as a combination of the images under ``basis`` (L point lights)."""

    label: str
    views: list[EvalView]
    light: PointLights | None = None
    weights: np.ndarray | None = None
    basis: PointLights | None = None
    extra: dict = field(default_factory=dict)


def view_cameras(views: list[EvalView]):
    """A :class:`~relightanyone.render.camera.Cameras` batch of the views (one image size)."""

    sizes = {(v.width, v.height) for v in views}
    if len(sizes) != 1:
        raise ValueError(f"evaluation views must share one image size, got {sorted(sizes)}")
    width, height = sizes.pop()
    return Cameras.create(
        np.stack([v.K for v in views]), np.stack([v.w2c for v in views]), width, height, dtype=torch.float32
    )


def stack_truth(views: list[EvalView]) -> tuple[torch.Tensor, torch.Tensor]:
    """(images (V, 3, H, W), masks (V, 1, H, W)) of the views."""
    images = torch.from_numpy(np.stack([v.image.transpose(2, 0, 1) for v in views]).astype(np.float32))
    masks = torch.from_numpy(np.stack([v.mask[None] for v in views]).astype(np.float32))
    return images, masks


def rig_patterns(dataset_dir: Path) -> dict[int, str]:
    """Rig light index -> its OLAT pattern name, from the dataset's lights.arrow."""

    return {int(row["index"]): str(row["pattern"]) for row in NormalizedDataset(dataset_dir).lights()}


def row_olat_cases(
    dataset_dir: Path, subject: str, rig: PointLights, light_indices: list[int], cameras: list[str]
) -> list[LightCase]:
    """OLAT ground truth from a subject's own OLAT rows (colour matrix applied as for fitting)."""

    rows = NormalizedTorchDataset(dataset_dir, subjects=subject, cameras=cameras, colour_matrix=LEARNED)
    patterns = rig_patterns(dataset_dir)
    row_cameras, row_patterns = rows.column("camera"), rows.column("pattern")
    cases = []
    for index in light_indices:
        first = {}  # camera -> its first row under this light
        for i, (camera, pattern) in enumerate(zip(row_cameras, row_patterns, strict=True)):
            if pattern == patterns[index]:
                first.setdefault(camera, i)
        views = [item_view(rows[first[camera]]) for camera in cameras if camera in first]
        if views:
            cases.append(LightCase(f"light {index:02d}", views, light=rig.olat(index)))
    return cases


def has_olat_rows(dataset_dir: Path, subject: str) -> bool:

    patterns = NormalizedTorchDataset(dataset_dir, subjects=subject).column("pattern")
    return any(p.startswith("olat-") for p in patterns)


def callable_olat_cases(
    true_image: Callable[[str, int], tuple[np.ndarray, np.ndarray]],
    rows: list[EvalView],
    rig: PointLights,
    light_indices: list[int],
) -> list[LightCase]:
    """OLAT ground truth from ``true_image(camera, light) -> (image (H, W, 3), mask (H, W))`` in the
    geometry of ``rows`` (views whose image and mask are replaced)."""
    cases = []
    for index in light_indices:
        views = []
        for row in rows:
            image, mask = true_image(row.camera, index)
            views.append(
                EvalView(
                    row.camera,
                    row.K,
                    row.w2c,
                    row.width,
                    row.height,
                    np.asarray(image, np.float32),
                    np.asarray(mask, np.float32),
                )
            )
        cases.append(LightCase(f"light {index:02d}", views, light=rig.olat(index)))
    return cases


@dataclass
class AnswerFrame:
    """A test subject's first full-on frame, tied to the world's answers.

    rows: (camera, K_row, width, height) of the chosen cameras; world_to_norm: (4, 4) A of
    :func:`world_to_normalized`; native: the answer cameras; row_masks: camera -> (H, W) mask of the
    row (the dataset's definition of the subject: the tracked head, cut below the neck line).
    """

    world_dataset: str
    subject: str
    frame: int
    rows: list[tuple[str, np.ndarray, int, int]]
    world_to_norm: np.ndarray
    native: dict[str, NativeCamera]
    row_masks: dict[str, np.ndarray] = field(default_factory=dict)

    def geometry(self, camera: str) -> tuple[np.ndarray, np.ndarray, int, int]:
        """(K, w2c, width, height) of the answer's view in the normalized space and the row's crop."""
        name, K, width, height = next(r for r in self.rows if r[0] == camera)
        w2c = self.native[camera].w2c @ np.linalg.inv(self.world_to_norm)
        return K, w2c, width, height


def answer_frame(
    answers: WorldAnswers, world_dataset: str, dataset_dir: Path, subject: str, cameras: list[str] | None
) -> AnswerFrame:
    """Tie a test subject's first full-on frame to the answers (cameras default to all of them)."""

    rows = NormalizedTorchDataset(dataset_dir, subjects=subject, patterns="full")
    native = answers.cameras(world_dataset)
    if not len(rows):
        raise InputError(f"{rows.source.path}: subject {subject!r} has no full-on rows")
    frames, row_cameras = rows.column("frame"), rows.column("camera")
    frame = min(frames)
    in_frame = [
        i for i, (f, c) in enumerate(zip(frames, row_cameras, strict=True)) if f == frame and c in native
    ]
    if not in_frame:
        raise InputError(
            f"{rows.source.path}: no camera of subject {subject!r} is among world dataset {world_dataset!r}'s cameras"
        )
    pairs = [(native[row_cameras[i]].w2c, rows.row(i).w2c) for i in in_frame]
    transform = world_to_normalized(pairs, answers.head_pose(world_dataset, subject, frame))
    chosen = [item_view(rows[i]) for i in in_frame if cameras is None or row_cameras[i] in cameras]
    return AnswerFrame(
        world_dataset,
        subject,
        frame,
        [(v.camera, v.K, int(v.width), int(v.height)) for v in chosen],
        transform,
        native,
        {v.camera: v.mask for v in chosen},
    )


def _warp(frame: AnswerFrame, camera: str, image: np.ndarray) -> np.ndarray:
    K, _, width, height = frame.geometry(camera)
    native = frame.native[camera]
    return warp_native_to_row(image, native.K, native.dist, K, width, height)


def answer_masks(answers: WorldAnswers, frame: AnswerFrame) -> dict[str, np.ndarray]:
    """Camera -> (H, W) mask of the subject: pixels lit by any answer light, warped into the crop, and
    inside the row's own mask.

    The row mask limits the comparison to what the datasets define as the subject (the head above the
    neck line), as Table 1's rows do: the model is trained to leave everything else empty.
    """
    lights = len(answers.answer_lights().positions)
    masks = {}
    for camera, *_ in frame.rows:
        total = sum(answers.olat_image(frame.world_dataset, frame.subject, camera, k) for k in range(lights))
        covered = (total.sum(axis=-1) > ANSWER_MASK_THRESHOLD).astype(np.float32)
        warped = _warp(frame, camera, covered[..., None])[..., 0]
        # Only pixels fully inside the subject: the warp blends edge pixels with the black background.
        covered_after_warp = torch.from_numpy((warped > 0.999).astype(np.float32))[None, None]
        inside = interior_mask(covered_after_warp)[0, 0].numpy()
        row_mask = frame.row_masks.get(camera)
        masks[camera] = inside if row_mask is None else inside * (row_mask > 0.5)
    return masks


def answer_lights_in_frame(
    answers: WorldAnswers, frame: AnswerFrame, rig: PointLights
) -> tuple[PointLights, list[int], float]:
    """The answer lights in the normalized space at the matched rig lights' intensities.

    Returns (lights (L), rig index of each, largest position mismatch in metres). The answer lights are
    lights of the D1 rig, so each takes its rig light's calibrated intensity (the model's light unit).
    """
    truth = answers.answer_lights()
    positions = truth.positions @ frame.world_to_norm[:3, :3].T + frame.world_to_norm[:3, 3]
    indices, worst = match_lights(positions, rig.positions.cpu().numpy())
    lights = PointLights(
        torch.as_tensor(positions, dtype=torch.float32),
        rig.intensities.cpu()[torch.as_tensor(indices)].float(),
    )
    return lights, indices, worst


def answer_olat_cases(
    answers: WorldAnswers,
    frame: AnswerFrame,
    rig: PointLights,
    light_indices: list[int] | None,
    masks: dict[str, np.ndarray],
) -> list[LightCase]:
    """OLAT ground truth from the answers for the answer lights whose rig index is in ``light_indices``."""
    lights, indices, worst = answer_lights_in_frame(answers, frame, rig)
    cases = []
    for k, index in enumerate(indices):
        if light_indices is not None and index not in light_indices:
            continue
        views = []
        for camera, *_ in frame.rows:
            K, w2c, width, height = frame.geometry(camera)
            image = answers.olat_image(frame.world_dataset, frame.subject, camera, k)
            views.append(EvalView(camera, K, w2c, width, height, _warp(frame, camera, image), masks[camera]))
        light = PointLights(lights.positions[k : k + 1], lights.intensities[k : k + 1])
        cases.append(LightCase(f"light {index:02d}", views, light=light, extra={"light_match_m": worst}))
    return cases


def relight_weights(olat: np.ndarray, relit: np.ndarray) -> np.ndarray:
    """(L, 3) weights w with ``relit ≈ Σ_k w[k] · olat[k]`` per channel, by least squares.

    olat: (L, P, 3) answer OLAT pixels; relit: (P, 3) the relit answer of the same pixels.
    """
    weights = np.zeros((olat.shape[0], 3))
    for channel in range(3):
        system = olat[:, :, channel].T.astype(np.float64)
        weights[:, channel] = np.linalg.lstsq(system, relit[:, channel].astype(np.float64), rcond=None)[0]
    return weights


def answer_envmap_cases(
    answers: WorldAnswers,
    frame: AnswerFrame,
    rig: PointLights,
    envmaps: list[str],
    masks: dict[str, np.ndarray],
) -> list[LightCase]:
    """Environment-map ground truth (the world's image-based relighting of the true OLAT answers).

    The world relit its answers as a fixed combination of the OLAT answers; the same weights, recovered
    from the answers by least squares, combine the model's OLAT renders, so both sides are relit alike.
    """
    lights, _, worst = answer_lights_in_frame(answers, frame, rig)
    first = frame.rows[0][0]
    olat = np.stack(
        [
            read_answer_image(answers.olat_path(frame.world_dataset, frame.subject, first, k))
            for k in range(len(lights))
        ]
    )
    covered = olat.sum(axis=(0, 3)) > ANSWER_MASK_THRESHOLD
    cases = []
    for name in envmaps:
        relit_native = read_answer_image(answers.relit_path(frame.world_dataset, frame.subject, first, name))
        weights = relight_weights(olat[:, covered], relit_native[covered])
        residual = np.abs(np.einsum("lc,lpc->pc", weights, olat[:, covered]) - relit_native[covered]).max()
        views = []
        for camera, *_ in frame.rows:
            K, w2c, width, height = frame.geometry(camera)
            image = read_answer_image(answers.relit_path(frame.world_dataset, frame.subject, camera, name))
            views.append(EvalView(camera, K, w2c, width, height, _warp(frame, camera, image), masks[camera]))
        cases.append(
            LightCase(
                name,
                views,
                weights=weights,
                basis=lights,
                extra={"weight_fit_max_residual": float(residual), "light_match_m": worst},
            )
        )
    return cases


def expected_olat_over_full_on(dataset_dir: Path) -> float:
    """Σ_k I_k(OLAT) / Σ_k I_k(full-on) from ``lights.arrow``: what :func:`olat_sum_over_full_on` should be.

    1 when the rig records no separate full-on intensities (``full_on_intensity_rgb`` null).
    """

    rows = NormalizedDataset(dataset_dir).lights()
    if not rows or any(row.get("full_on_intensity_rgb") is None for row in rows):
        return 1.0
    olat = sum(float(np.sum(row["intensity_rgb"])) for row in rows)
    full = sum(float(np.sum(row["full_on_intensity_rgb"])) for row in rows)
    return olat / full if full > 0 else 1.0


def olat_sum_over_full_on(dataset_dir: Path, subject: str, cameras: list[str]) -> float | None:
    """Σ_k OLAT_k / full-on (pixel sums, mean over cameras with every OLAT pattern); 1 when both share a unit.

    A full-on frame is every rig light at once, so in one radiometric unit it equals the sum of the OLAT
    frames (up to the small head motion between frames). None when no camera has all patterns.
    """

    rows = NormalizedTorchDataset(dataset_dir, subjects=subject)
    patterns = rig_patterns(dataset_dir)
    row_cameras, row_patterns = rows.column("camera"), rows.column("pattern")

    def pixel_sum(index: int) -> float:
        return float(image_hwc(rows[index]).sum())

    ratios = []
    for camera in cameras:
        found = {}  # pattern -> the camera's first row of it
        for pattern in ["full", *patterns.values()]:
            first = next(
                (
                    i
                    for i, (c, p) in enumerate(zip(row_cameras, row_patterns, strict=True))
                    if (c, p) == (camera, pattern)
                ),
                None,
            )
            if first is None:
                break
            found[pattern] = first
        else:
            total = sum(pixel_sum(found[p]) for p in patterns.values())
            full = pixel_sum(found["full"])
            if full > 0:
                ratios.append(total / full)
    return float(np.mean(ratios)) if ratios else None
