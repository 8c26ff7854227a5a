"""Views to fit a subject to: images, masks, cameras and the tracked mesh, read from a normalized dataset
through its :class:`~relightanyone.format.torch_dataset.NormalizedTorchDataset`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.format.schema import PADDING_WEIGHT_TOLERANCE, make_mesh_key
from relightanyone.format.torch_dataset import LEARNED, NormalizedTorchDataset, image_hwc
from relightanyone.render.camera import resize_intrinsics


@dataclass
class FitViews:
    """The input of a fit: V views of one subject and frame, one image size.

    images (V, 3, H, W) linear RGB; masks (V, 1, H, W); K (V, 3, 3); w2c (V, 4, 4) float32;
    tracked_vertices (Vtx, 3) or None; keys and cameras name the rows; valid (V, 1, H, W) 0/1, 0 on the
    padding past the source image (None: every pixel).
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
    valid: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.valid is None:
            self.valid = torch.ones_like(self.masks)

    def __len__(self) -> int:
        return self.images.shape[0]

    def to(self, device: torch.device | str) -> FitViews:
        """A copy with the images, masks, cameras and tracked mesh on ``device``."""
        tracked = self.tracked_vertices
        return dataclasses.replace(
            self,
            images=self.images.to(device),
            masks=self.masks.to(device),
            K=self.K.to(device),
            w2c=self.w2c.to(device),
            tracked_vertices=None if tracked is None else tracked.to(device),
        )


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
    if image_scale <= 0:
        raise InputError(f"image_scale must be positive, got {image_scale}")
    rows = NormalizedTorchDataset(dataset_dir, subjects=subject, patterns=pattern, colour_matrix=LEARNED)
    dataset = rows.source
    if subject not in dataset.subjects:
        raise InputError(f"{dataset.path}: no subject {subject!r}; it has {', '.join(dataset.subjects[:12])}")
    if not len(rows):
        raise InputError(
            f"{dataset.path}: subject {subject!r} has no rows with pattern {pattern!r}; "
            f"the dataset's patterns are {', '.join(dataset.patterns[:12])}"
        )
    # Frames and cameras from the small index, so no image row is read before the views are known.
    frames, row_cameras = rows.column("frame"), rows.column("camera")
    frame = min(frames) if frame is None else int(frame)
    chosen = [i for i, f in enumerate(frames) if f == frame]
    if cameras is not None:
        by_camera = {row_cameras[i]: i for i in chosen}
        missing = [c for c in cameras if c not in by_camera]
        if missing:
            raise InputError(
                f"{dataset.path}: subject {subject!r} frame {frame} pattern {pattern!r} has no camera "
                f"{missing}; it has {sorted(by_camera)}"
            )
        chosen = [by_camera[c] for c in cameras]
    if not chosen:
        raise InputError(f"{dataset.path}: subject {subject!r} has no {pattern!r} rows at frame {frame}")
    items = [rows[i] for i in chosen]
    sizes = {(item["width"], item["height"]) for item in items}
    if len(sizes) != 1:
        raise InputError(
            f"{dataset.path}: the chosen views have several image sizes {sorted(sizes)}; pick cameras of one size"
        )
    images, masks, valid = zip(*(scaled_image_and_mask(item, image_scale) for item in items), strict=True)
    tracked = dataset.meshes().get(make_mesh_key(subject, frame))
    return FitViews(
        images=torch.stack(images),
        masks=torch.stack(masks),
        valid=torch.stack(valid),
        K=torch.tensor(
            np.stack([resize_intrinsics(item["K"].numpy(), image_scale, image_scale) for item in items]),
            dtype=torch.float32,
        ),
        w2c=torch.stack([item["w2c"] for item in items]).to(torch.float32),
        tracked_vertices=None if tracked is None else torch.from_numpy(np.asarray(tracked, dtype=np.float32)),
        subject=subject,
        frame=frame,
        dataset=dataset.name,
        pattern=pattern,
        keys=[item["key"] for item in items],
        cameras=[item["camera"] for item in items],
    )


def scaled_image_and_mask(item: dict, scale: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(image (3, h, w), mask (1, h, w), valid (1, h, w)) of a dataset item resized by ``scale`` (OpenCV
    area filter; the item's own tensors at scale 1). A resized pixel is valid when every pixel it averages
    is."""
    if scale == 1.0:
        return item["image"], item["mask"], item["valid"]
    size = (max(1, round(item["width"] * scale)), max(1, round(item["height"] * scale)))
    image = cv2.resize(image_hwc(item), size, interpolation=cv2.INTER_AREA)
    mask = cv2.resize(item["mask"][0].numpy(), size, interpolation=cv2.INTER_AREA)
    coverage = cv2.resize(item["valid"][0].numpy(), size, interpolation=cv2.INTER_AREA)
    valid = (coverage >= 1.0 - PADDING_WEIGHT_TOLERANCE).astype(np.float32)
    return (
        torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32)),
        torch.from_numpy(np.asarray(mask, dtype=np.float32)[None] * valid),
        torch.from_numpy(valid[None]),
    )
