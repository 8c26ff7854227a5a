"""A map-style ``torch.utils.data.Dataset`` over one normalized dataset.

Each item is a dict::

    image          (3, H, W) float32, scene-linear, colour matrix applied when one is given
    mask           (1, H, W) float32 in [0, 1]
    K              (3, 3) float32
    w2c            (4, 4) float32
    colour_matrix  (3, 3) float32, the matrix the dataset was already normalized with
    key, dataset, subject, camera, pattern, split: str;  frame: int

Shard memory maps are opened lazily in each worker (the reader drops them on pickling), so it works with
``DataLoader(num_workers > 0)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset


class NormalizedTorchDataset(torch.utils.data.Dataset):
    """Rows of ``path`` filtered by subject, split, pattern or camera, in key order.

    ``colour_matrix`` (3, 3), when given, is applied on load: ``rgb = colour_matrix @ rgb`` per pixel.
    """

    def __init__(
        self,
        path: Path | str | NormalizedDataset,
        splits: list[str] | str | None = None,
        patterns: list[str] | str | None = None,
        subjects: list[str] | str | None = None,
        cameras: list[str] | str | None = None,
        colour_matrix: np.ndarray | torch.Tensor | None = None,
    ):
        self.source = path if isinstance(path, NormalizedDataset) else NormalizedDataset(path)
        self.keys = self.source.select(subjects=subjects, cameras=cameras, patterns=patterns, splits=splits)
        if colour_matrix is not None:
            colour_matrix = torch.as_tensor(np.asarray(colour_matrix, dtype=np.float32))
            if colour_matrix.shape != (3, 3):
                raise ValueError(f"colour_matrix must be (3, 3), got {tuple(colour_matrix.shape)}")
        self.colour_matrix = colour_matrix

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, index: int) -> dict[str, Any]:
        row, image, mask = self.source.decoded(self.keys[index])
        if image.shape[:2] != (row.height, row.width) or mask.shape != (row.height, row.width):
            raise InputError(
                f"{self.source.path}: row {row.key!r} declares {row.width}x{row.height} but decodes to "
                f"image {image.shape[:2]} and mask {mask.shape}"
            )
        image_tensor = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).contiguous()
        if self.colour_matrix is not None:
            image_tensor = torch.einsum("ij,jhw->ihw", self.colour_matrix, image_tensor)
        return {
            "image": image_tensor,
            "mask": torch.from_numpy(mask)[None],
            "K": torch.from_numpy(row.K.astype(np.float32)),
            "w2c": torch.from_numpy(row.w2c.astype(np.float32)),
            "colour_matrix": torch.from_numpy(row.colour_matrix.astype(np.float32)),
            "key": row.key,
            "dataset": row.dataset,
            "subject": row.subject,
            "frame": row.frame,
            "camera": row.camera,
            "pattern": row.pattern,
            "split": row.split,
        }
