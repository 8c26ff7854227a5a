"""Fit inputs under an unknown lighting: held-out subjects lit as no capture the model knows.

The OLAT dataset's own full-on frames of a held-out subject are lit by the calibrated full-on rig, which
is also where the fit's lighting prior starts, so fitting them would hand the fit the true lighting. The
evaluation's inputs are instead the world's renders of the subject under a lighting drawn for it
(:mod:`relightanyone.synth.input_lighting`: other level, colour, per-light gains and an environment map),
composed from its true OLAT answers and warped into the normalized rows' crops like every answer. The fit
is told nothing of it: its lighting prior and start stay the full-on rig recorded with the OLAT dataset's
training captures (``lights.arrow``).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import torch

from relightanyone.evaluation.cases import AnswerFrame
from relightanyone.evaluation.truth import WorldAnswers, warp_native_to_row
from relightanyone.model.fit.views import FitViews
from relightanyone.synth.input_lighting import InputLighting, input_lighting
from relightanyone.synth.world import DATASET_MODULES

INPUT_PATTERN = "unknown-lighting"  # the FitViews pattern of these inputs


def world_seed(answers: WorldAnswers) -> int:
    """The world's seed (``world.json``); 0 for an answers folder written without one (test worlds)."""
    path = answers.world / "world.json"
    return int(json.loads(path.read_text()).get("seed", 0)) if path.is_file() else 0


def full_on_scale(answers: WorldAnswers, world_dataset: str) -> float:
    """Full-on exposure of one light relative to its OLAT image in ``world_dataset`` (1 when not recorded)."""
    truth = json.loads((answers.root / world_dataset / "truth.json").read_text())
    return float(truth.get("extra", {}).get("full_on_scale", 1.0))


def subject_input_lighting(answers: WorldAnswers, world_dataset: str, subject: str) -> InputLighting:
    """The world's input lighting of a held-out subject (deterministic in the world seed and the name)."""
    order = list(DATASET_MODULES) if world_dataset in DATASET_MODULES else answers.datasets
    lights = answers.answer_lights()
    return input_lighting(
        world_seed(answers),
        order.index(world_dataset),
        subject,
        lights.positions,
        lights.intensities,
        full_on_scale(answers, world_dataset),
    )


def relit_input_image(
    answers: WorldAnswers, frame: AnswerFrame, camera: str, weights: np.ndarray
) -> np.ndarray:
    """(H, W, 3) the subject of ``frame`` under ``weights`` (L, 3) of the answer lights, in the row's crop."""
    native = sum(
        weights[k].astype(np.float32) * answers.olat_image(frame.world_dataset, frame.subject, camera, k)
        for k in range(len(weights))
    )
    K, _, width, height = frame.geometry(camera)
    view = frame.native[camera]
    return warp_native_to_row(native, view.K, view.dist, K, width, height)


def unknown_lighting_views(
    answers: WorldAnswers,
    frame: AnswerFrame,
    lighting: InputLighting,
    masks: dict[str, np.ndarray],
    dataset: str,
    tracked_vertices: torch.Tensor | None,
    unit_scale: np.ndarray | None = None,
) -> FitViews:
    """Fit views of ``frame``'s cameras under ``lighting``: images (V, 3, H, W), ``masks`` per camera, the
    answers' cameras in the normalized space, the tracked mesh. ``unit_scale`` (3,) converts answer
    radiance to the rows' unit when the two differ."""
    scale = np.ones(3, np.float32) if unit_scale is None else np.asarray(unit_scale, np.float32)
    images, mask_list, Ks, w2cs = [], [], [], []
    for camera, *_ in frame.rows:
        K, w2c, _, _ = frame.geometry(camera)
        image = relit_input_image(answers, frame, camera, lighting.weights) * scale
        images.append(torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))))
        mask_list.append(torch.from_numpy(np.asarray(masks[camera], np.float32)[None]))
        Ks.append(K)
        w2cs.append(w2c)
    cameras = [row[0] for row in frame.rows]
    return FitViews(
        images=torch.stack(images).float(),
        masks=torch.stack(mask_list),
        K=torch.tensor(np.stack(Ks), dtype=torch.float32),
        w2c=torch.tensor(np.stack(w2cs), dtype=torch.float32),
        tracked_vertices=tracked_vertices,
        subject=frame.subject,
        frame=frame.frame,
        dataset=dataset,
        pattern=INPUT_PATTERN,
        keys=[f"{dataset}/{frame.subject}/{frame.frame:06d}/{c}/{INPUT_PATTERN}" for c in cameras],
        cameras=cameras,
    )


def select_views(views: FitViews, cameras: list[str]) -> FitViews:
    """The views of ``cameras`` only (in that order), e.g. one camera for a single-image fit."""
    index = [views.cameras.index(c) for c in cameras]
    return dataclasses.replace(
        views,
        images=views.images[index],
        masks=views.masks[index],
        K=views.K[index],
        w2c=views.w2c[index],
        keys=[views.keys[i] for i in index],
        cameras=list(cameras),
    )
