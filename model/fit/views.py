"""Views to fit a subject to: images, masks, cameras and the tracked mesh, read from a normalized dataset."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from relightanyone.align.colour import read_learned_colour_matrix
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import make_mesh_key
from relightanyone.render.camera import resize_intrinsics


@dataclass
class FitViews:
    """The input of a fit: V views of one subject and frame, one image size.

    images (V, 3, H, W) linear RGB; masks (V, 1, H, W); K (V, 3, 3); w2c (V, 4, 4) float32;
    tracked_vertices (Vtx, 3) or None; keys and cameras name the rows.
    """

    images: torch.Tensor
    masks: torch.Tensor
    K: torch.Tensor
    w2c: torch.Tensor
    tracked_vertices: torch.Tensor | None
    subject: str
    frame: int
    dataset: str
    pattern: str
    keys: list[str] = field(default_factory=list)
    cameras: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return self.images.shape[0]


def load_fit_views(
    dataset_dir: Path,
    subject: str,
    frame: int | None = None,
    cameras: list[str] | None = None,
    pattern: str = "full",
    image_scale: float = 1.0,
) -> FitViews:
    """Read the views of ``subject`` in a normalized dataset (any split), its learned colour matrix applied.

    ``frame`` defaults to the subject's first frame with ``pattern`` rows; ``cameras`` to all of them (one
    camera makes a single-image fit). ``image_scale`` resizes the images (OpenCV area filter) and K.
    """
    import cv2

    if image_scale <= 0:
        raise ValueError(f"image_scale must be positive, got {image_scale}")
    dataset = NormalizedDataset(dataset_dir)
    if subject not in dataset.subjects:
        raise ValueError(f"{dataset.path}: no subject {subject!r}; it has {', '.join(dataset.subjects[:12])}")
    keys = dataset.select(subjects=subject, patterns=pattern)
    if not keys:
        raise ValueError(
            f"{dataset.path}: subject {subject!r} has no rows with pattern {pattern!r}; "
            f"the dataset's patterns are {', '.join(dataset.patterns[:12])}"
        )
    if frame is None:
        # Frames from the small index, so no image row is read before the frame is known.
        frame_of = dict(
            zip(
                dataset.index.column("key").to_pylist(),
                dataset.index.column("frame").to_pylist(),
                strict=True,
            )
        )
        frame = min(int(frame_of[k]) for k in keys)
    rows = [dataset.row(k) for k in dataset.select(subjects=subject, patterns=pattern, frames=int(frame))]
    frame = int(frame)
    if cameras is not None:
        by_camera = {r.camera: r for r in rows}
        missing = [c for c in cameras if c not in by_camera]
        if missing:
            raise ValueError(
                f"{dataset.path}: subject {subject!r} frame {frame} pattern {pattern!r} has no camera "
                f"{missing}; it has {sorted(by_camera)}"
            )
        rows = [by_camera[c] for c in cameras]
    if not rows:
        raise ValueError(f"{dataset.path}: subject {subject!r} has no {pattern!r} rows at frame {frame}")
    sizes = {(r.width, r.height) for r in rows}
    if len(sizes) != 1:
        raise ValueError(
            f"{dataset.path}: the chosen views have several image sizes {sorted(sizes)}; pick cameras of one size"
        )
    matrix = read_learned_colour_matrix(dataset.path)
    images, masks, Ks = [], [], []
    for row in rows:
        _, image, mask = dataset.decoded(row.key)
        if matrix is not None:
            image = image @ matrix.T.astype(np.float32)
        if image_scale != 1.0:
            size = (max(1, round(row.width * image_scale)), max(1, round(row.height * image_scale)))
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            mask = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        images.append(np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32))
        masks.append(np.asarray(mask, dtype=np.float32)[None])
        Ks.append(resize_intrinsics(row.K, image_scale, image_scale))
    tracked = dataset.meshes().get(make_mesh_key(subject, frame))
    return FitViews(
        images=torch.from_numpy(np.stack(images)),
        masks=torch.from_numpy(np.stack(masks)),
        K=torch.tensor(np.stack(Ks), dtype=torch.float32),
        w2c=torch.tensor(np.stack([r.w2c for r in rows]), dtype=torch.float32),
        tracked_vertices=None if tracked is None else torch.from_numpy(np.asarray(tracked, dtype=np.float32)),
        subject=subject,
        frame=frame,
        dataset=dataset.name,
        pattern=pattern,
        keys=[r.key for r in rows],
        cameras=[r.camera for r in rows],
    )
