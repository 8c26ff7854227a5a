"""A map-style ``torch.utils.data.Dataset`` over one normalized dataset: the way the model reads rows.

Stage-1 and stage-2 training, the single-stage baseline, fitting and evaluation all read their images
through :class:`NormalizedTorchDataset`. Each item is a dict::

    image          (3, H, W) float32, scene-linear, the colour matrix applied (``rgb = M @ rgb``) when given
    mask           (1, H, W) float32 in [0, 1], zero wherever ``valid`` is
    valid          (1, H, W) float32, 1 where the pixel comes from the source image, 0 where it reaches the
                   zero padding past the source's edge: losses and metrics weigh pixels by it
    K              (3, 3) float64, pixels of the stored image
    w2c            (4, 4) float64, OpenCV world-to-camera
    colour_matrix  (3, 4) float32, the correction ingest already applied (``rgb = M[:, :3] @ src + M[:, 3]``)
    index          int, the item's position in this dataset
    key, dataset, subject, camera, pattern, split: str;  frame, width, height: int

``K`` and ``w2c`` stay in the stored float64, so code that crops or rescales an image shifts the camera
before rounding it to float32 once; :func:`random_crop` is the training crop of an item (image, mask,
valid pixels and ``K`` together). :func:`collate_rows` stacks items into a batch
(``DataLoader(dataset, collate_fn=collate_rows)``).

A row is fetched by key from the memory-mapped shards (O(1) in the number of rows); the selection
(filters, keys) is made once, on the small index. Shard memory maps are opened lazily in each process
(the reader drops them on pickling), so the dataset works with ``DataLoader(num_workers > 0)``.

The trainers read their batches through :func:`iteration_loader`: a ``DataLoader`` whose item is the batch
of one iteration (:class:`IterationBatches`), made from these rows by worker processes ahead of the step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relightanyone.align.colour import LearnedColour
from relightanyone.errors import InputError
from relightanyone.format.colour_alignment import read_learned_colour
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import ImageRow
from relightanyone.render.camera import crop_intrinsics

INDEX_COLUMNS = ("key", "subject", "frame", "camera", "pattern", "split")
LEARNED = "learned"  # colour_matrix: the dataset's learned matrices (colour_alignment.json) when it has them


class NormalizedTorchDataset(torch.utils.data.Dataset):
    """Rows of ``path`` filtered by subject, frame, camera, pattern and split, in key order; or exactly
    ``keys``, in their order.

    ``colour_matrix``: None (images as stored), a (3, 3) matrix, or ``"learned"``: the dataset's learned
    alignment (``colour_alignment.json``, written by the colour warm-up) when the folder has one, the row's
    camera's own matrix where it has one. It is applied on load, ``rgb = colour_matrix @ rgb`` per pixel.
    """

    def __init__(
        self,
        path: Path | str | NormalizedDataset,
        splits: list[str] | str | None = None,
        patterns: list[str] | str | None = None,
        subjects: list[str] | str | None = None,
        cameras: list[str] | str | None = None,
        frames: list[int] | int | None = None,
        keys: Sequence[str] | None = None,
        colour_matrix: np.ndarray | torch.Tensor | str | None = None,
    ):
        self.source = path if isinstance(path, NormalizedDataset) else NormalizedDataset(path)
        selected = self.source.select(
            subjects=subjects, cameras=cameras, patterns=patterns, splits=splits, frames=frames
        )
        if keys is not None:
            missing = [k for k in keys if k not in self.source]
            if missing:
                raise ValueError(f"{self.source.path}: no image rows {missing[:4]}")
            chosen = set(selected)
            selected = [k for k in keys if k in chosen]
        self.keys = selected
        self._positions = np.asarray([self.source.position(k) for k in selected], dtype=np.int64)
        if isinstance(colour_matrix, str):
            if colour_matrix != LEARNED:
                raise ValueError(f"colour_matrix must be a (3, 3) matrix, None or {LEARNED!r}")
            self.colour: LearnedColour | None = read_learned_colour(self.source.path)
        elif colour_matrix is not None:
            fixed = np.asarray(colour_matrix, dtype=np.float64)
            if fixed.shape != (3, 3):
                raise ValueError(f"colour_matrix must be (3, 3), got {tuple(fixed.shape)}")
            self.colour = LearnedColour(fixed)
        else:
            self.colour = None

    def colour_matrix_of(self, camera: str) -> np.ndarray | None:
        """The (3, 3) matrix applied to ``camera``'s images on load, None when none is."""
        return None if self.colour is None else self.colour.for_camera(camera)

    @property
    def name(self) -> str:
        return self.source.name

    def __len__(self) -> int:
        return len(self.keys)

    def column(self, name: str) -> list:
        """One index column (``key``, ``subject``, ``frame``, ``camera``, ``pattern``, ``split``) of the
        selected rows, in item order; no shard is read."""
        if name not in INDEX_COLUMNS:
            raise ValueError(f"no index column {name!r}; the index has {', '.join(INDEX_COLUMNS)}")
        return self.source.index.column(name).take(self._positions).to_pylist()

    def row(self, index: int) -> ImageRow:
        """The stored row of item ``index`` (cameras, sizes, crop; image and mask still encoded)."""
        return self.source.row(self.keys[index])

    def __getitem__(self, index: int) -> dict[str, Any]:
        row, image, mask = self.source.decoded(self.keys[index])
        if image.shape[:2] != (row.height, row.width) or mask.shape != (row.height, row.width):
            raise InputError(
                f"{self.source.path}: row {row.key!r} declares {row.width}x{row.height} but decodes to "
                f"image {image.shape[:2]} and mask {mask.shape}"
            )
        matrix = self.colour_matrix_of(row.camera)
        if matrix is not None:
            image = image @ matrix.T.astype(np.float32)
        valid = row.valid_pixels()
        return {
            "image": torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32)),
            # Masks exclude padding by the format's rule; applied again so no reader can count it.
            "mask": torch.from_numpy(mask * valid)[None],
            "valid": torch.from_numpy(valid.astype(np.float32))[None],
            "K": torch.from_numpy(row.K),
            "w2c": torch.from_numpy(row.w2c),
            "colour_matrix": torch.from_numpy(row.colour_matrix.astype(np.float32)),
            "index": int(index),
            "key": row.key,
            "dataset": row.dataset,
            "subject": row.subject,
            "frame": row.frame,
            "camera": row.camera,
            "pattern": row.pattern,
            "split": row.split,
            "width": row.width,
            "height": row.height,
        }


@dataclass(frozen=True)
class CropBox:
    """A crop window in stored-image pixels; may extend past the image (padded with zeros, mask 0)."""

    x0: int
    y0: int
    size: int


def choose_crop(mask: np.ndarray, size: int, rng: np.random.Generator) -> CropBox:
    """A ``size``×``size`` window centred on a random foreground pixel, kept inside the image when the
    image is large enough (otherwise centred on the image, padded).

    mask: (H, W) float or bool foreground.
    """
    height, width = mask.shape
    foreground = np.flatnonzero(np.asarray(mask) > 0.5)
    if foreground.size:
        centre = int(foreground[rng.integers(0, foreground.size)])
        cy, cx = divmod(centre, width)
    else:
        cy, cx = height // 2, width // 2

    def place(centre: int, extent: int) -> int:
        if extent <= size:
            return (extent - size) // 2
        return int(np.clip(centre - size // 2, 0, extent - size))

    return CropBox(x0=place(cx, width), y0=place(cy, height), size=size)


def crop_array(array: np.ndarray, box: CropBox) -> np.ndarray:
    """Crop (C, H, W) to (C, size, size), filling the part outside the image with zeros."""
    channels, height, width = array.shape
    out = np.zeros((channels, box.size, box.size), dtype=array.dtype)
    src_x0, src_y0 = max(box.x0, 0), max(box.y0, 0)
    src_x1, src_y1 = min(box.x0 + box.size, width), min(box.y0 + box.size, height)
    if src_x1 > src_x0 and src_y1 > src_y0:
        out[:, src_y0 - box.y0 : src_y1 - box.y0, src_x0 - box.x0 : src_x1 - box.x0] = array[
            :, src_y0:src_y1, src_x0:src_x1
        ]
    return out


def random_crop(item: dict[str, Any], size: int, rng: np.random.Generator) -> dict[str, Any]:
    """A dataset item (:class:`NormalizedTorchDataset`) cropped to the
    window :func:`choose_crop` draws from its mask: image (3, size, size), mask and valid (1, size, size)
    and K (float64) of the crop; the other fields as they are. A window past the image's edge is padding:
    invalid."""
    box = choose_crop(item["mask"][0].numpy(), size, rng)
    cropped = {
        name: torch.from_numpy(crop_array(item[name].numpy(), box))
        for name in ("image", "mask", "valid")
        if name in item
    }
    return {**item, **cropped, "K": torch.from_numpy(crop_intrinsics(item["K"].numpy(), box.x0, box.y0))}


def image_hwc(item: dict[str, Any]) -> np.ndarray:
    """(H, W, 3) float32, C-contiguous: an item's image laid out as NumPy and OpenCV code reads it."""
    return np.ascontiguousarray(item["image"].permute(1, 2, 0).numpy())


def collate_rows(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """A batch of items: tensors stacked into ``(B, ...)``, every other field as a list of B values.

    Tensors of one field must share a shape (crop first when the rows differ in size).
    """
    if not items:
        raise ValueError("no items to collate")
    batch: dict[str, Any] = {}
    for name, first in items[0].items():
        values = [item[name] for item in items]
        if isinstance(first, torch.Tensor):
            shapes = {tuple(v.shape) for v in values}
            if len(shapes) > 1:
                raise ValueError(f"items of one batch differ in {name} shape: {sorted(shapes)}")
            batch[name] = torch.stack(values)
        else:
            batch[name] = values
    return batch


class IterationBatches(torch.utils.data.Dataset):
    """Training batches by iteration: item ``i`` is ``make_batch(start + i)``, for ``start <= iteration < stop``.

    A trainer's batch is a function of its iteration alone (its samplers are stateless and read rows
    through :class:`NormalizedTorchDataset`), so a :func:`iteration_loader` with worker processes yields
    exactly what a synchronous loop would, just earlier. ``make_batch`` must pickle (workers get a copy).
    """

    def __init__(self, make_batch, start: int, stop: int) -> None:
        self.make_batch, self.start, self.stop = make_batch, int(start), int(stop)

    def __len__(self) -> int:
        return max(self.stop - self.start, 0)

    def __getitem__(self, index: int) -> Any:
        if not 0 <= index < len(self):
            raise IndexError(index)
        return self.make_batch(self.start + index)


def iteration_loader(
    make_batch, start: int, stop: int, workers: int = 0, pin_memory: bool = False, prefetch: int = 2
) -> torch.utils.data.DataLoader:
    """A ``DataLoader`` over :class:`IterationBatches`, in iteration order: ``workers`` processes make the
    next batches while the current one trains (``prefetch`` batches each, workers kept between epochs);
    ``pin_memory`` (for CUDA) puts them in page-locked memory so the copy to the GPU can overlap. With no
    workers the batches are made in the training process, when asked for."""
    return torch.utils.data.DataLoader(
        IterationBatches(make_batch, start, stop),
        batch_size=None,
        shuffle=False,
        num_workers=workers,
        pin_memory=pin_memory,
        prefetch_factor=prefetch if workers > 0 else None,
        persistent_workers=workers > 0,
    )
