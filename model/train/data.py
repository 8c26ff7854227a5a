"""Training and held-out views of several normalized datasets for stage 1.

Only full-on rows (``pattern == "full"``) of training subjects (``split == "train"``) are used. Each
subject keeps a few cameras aside (:func:`relightanyone.model.train.sampling.held_out_cameras`, a
different few for each subject of a rig) for the held-out PSNR/SSIM. Subjects are keyed
``<dataset>/<subject>`` (names only need to be unique within a dataset). Each dataset's rows are a
:class:`~relightanyone.format.torch_dataset.NormalizedTorchDataset`: images stream from the
memory-mapped shards one row at a time; nothing but the small index and the tracked meshes is held in
memory.

A dataset folder carries its template mesh as ``template.obj``; all datasets trained together must
share one template topology. A learned colour matrix (``colour_alignment.json``, written by the colour
warm-up; the camera's own where it has one) is applied on load: ``rgb = M @ rgb``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.format.schema import MANIFEST_NAME, TEMPLATE_NAME, make_mesh_key
from relightanyone.format.torch_dataset import LEARNED, NormalizedTorchDataset, collate_rows, random_crop
from relightanyone.model.train.sampling import (
    CROP_STREAM,
    held_out_cameras,
    iteration_generator,
)
from relightanyone.render.mesh import load_obj

FULL_ON_PATTERN = "full"
TRAIN_SPLIT = "train"


def view_batch(
    items: list[dict[str, Any]], tracked: list[np.ndarray | None], subject_index: list[int]
) -> dict[str, torch.Tensor]:
    """A training batch of B dataset items of one size (``random_crop`` output) with their meshes.

    Returns image (B, 3, H, W), mask and valid (B, 1, H, W), K (B, 3, 3) and w2c (B, 4, 4) float32,
    tracked (B, V, 3) (zeros for a view without a mesh), has_mesh (B,) float, subject_index (B,) int64.
    """
    batch = collate_rows(items)
    vertex_count = next((t.shape[0] for t in tracked if t is not None), 0)
    return {
        "image": batch["image"],
        "mask": batch["mask"],
        "valid": batch["valid"],
        "K": batch["K"].to(torch.float32),
        "w2c": batch["w2c"].to(torch.float32),
        "tracked": torch.from_numpy(
            np.stack([t if t is not None else np.zeros((vertex_count, 3), np.float32) for t in tracked])
        ),
        "has_mesh": torch.tensor([float(t is not None) for t in tracked]),
        "subject_index": torch.tensor(subject_index, dtype=torch.long),
    }


@dataclass(frozen=True)
class ViewRef:
    """One image row: which dataset, its item there and key, the identity row and the frame of its
    tracked mesh."""

    dataset_index: int
    position: int  # item index in ``Stage1Data.rows[dataset_index]``
    key: str
    subject_index: int
    subject: str  # subject name inside its dataset
    frame: int
    camera: str


class Stage1Data:
    """Views of several normalized datasets, split into training and held-out cameras.

    Args:
        dataset_dirs: normalized dataset folders (``<root>/<dataset>``).
        held_out_per_subject: cameras per subject kept out of training.
        apply_learned_colour: apply each dataset's ``colour_alignment.json`` when it exists (off during
            the colour warm-up, which learns those matrices from the raw colours).
    """

    def __init__(
        self, dataset_dirs: list[Path], held_out_per_subject: int, apply_learned_colour: bool = True
    ):

        if not dataset_dirs:
            raise InputError("no dataset given: pass at least one normalized dataset folder with --data")
        self.dirs = [Path(d) for d in dataset_dirs]
        colour = LEARNED if apply_learned_colour else None
        self.rows = [
            NormalizedTorchDataset(d, patterns=FULL_ON_PATTERN, splits=TRAIN_SPLIT, colour_matrix=colour)
            for d in self.dirs
        ]
        self.names = [rows.name for rows in self.rows]
        if len(set(self.names)) != len(self.names):
            raise InputError(f"datasets must have distinct names, got {self.names}")
        self.template_path = self._check_templates()
        self.subjects: list[str] = []
        self.train_views: list[list[ViewRef]] = []
        self.held_out_views: list[list[ViewRef]] = []
        self._meshes: list[dict[str, np.ndarray]] = []
        for index, rows in enumerate(self.rows):
            train, held_out = self._split_views(index, rows, held_out_per_subject)
            if not train:
                raise InputError(
                    f"{rows.source.path}: no full-on training views (rows with pattern 'full' and split 'train')"
                )
            self.train_views.append(train)
            self.held_out_views.append(held_out)
            self._meshes.append(rows.source.meshes())

    def _check_templates(self) -> Path:

        paths = [d / TEMPLATE_NAME for d in self.dirs]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise FileNotFoundError(
                f"template mesh missing: {', '.join(missing)}; ingest writes {TEMPLATE_NAME} beside {MANIFEST_NAME} "
                "(re-run ingest, or copy the template OBJ of the tracked meshes there)"
            )
        counts = {str(p): len(load_obj(p).vertices) for p in paths}
        if len(set(counts.values())) > 1:
            raise InputError(
                f"datasets trained together must share one template topology; vertex counts: {counts}"
            )
        return paths[0]

    def _split_views(
        self, dataset_index: int, rows: NormalizedTorchDataset, held_out_per_subject: int
    ) -> tuple[list, list]:
        columns = {name: rows.column(name) for name in ("key", "subject", "frame", "camera")}
        rows_by_subject: dict[str, list[int]] = {}
        for position, subject in enumerate(columns["subject"]):
            rows_by_subject.setdefault(subject, []).append(position)
        train: list[ViewRef] = []
        held_out: list[ViewRef] = []
        for place, subject in enumerate(sorted(rows_by_subject)):
            subject_index = len(self.subjects)
            self.subjects.append(f"{rows.name}/{subject}")
            positions = rows_by_subject[subject]
            aside = held_out_cameras([columns["camera"][p] for p in positions], held_out_per_subject, place)
            for position in positions:
                view = ViewRef(
                    dataset_index=dataset_index,
                    position=position,
                    key=columns["key"][position],
                    subject_index=subject_index,
                    subject=subject,
                    frame=int(columns["frame"][position]),
                    camera=columns["camera"][position],
                )
                (held_out if view.camera in aside else train).append(view)
        return train, held_out

    @property
    def views_per_dataset(self) -> list[int]:
        return [len(views) for views in self.train_views]

    def subject_views(self, subject_index: int, held_out_only: bool = False) -> list[ViewRef]:
        """Views of one identity row (its held-out cameras only, or all its cameras)."""
        groups = (
            self.held_out_views
            if held_out_only
            else [t + h for t, h in zip(self.train_views, self.held_out_views, strict=True)]
        )
        return sorted(
            (v for views in groups for v in views if v.subject_index == subject_index), key=lambda v: v.key
        )

    def tracked_vertices(self, view: ViewRef) -> np.ndarray | None:
        """(V, 3) tracked mesh of the view's (subject, frame); the subject's first frame when that frame has
        none; None when the subject has no tracked mesh at all."""

        meshes = self._meshes[view.dataset_index]
        exact = meshes.get(make_mesh_key(view.subject, view.frame))
        if exact is not None:
            return exact
        prefix = f"{view.subject}/"
        for key in sorted(meshes):
            if key.startswith(prefix):
                return meshes[key]
        return None

    def load_view(self, view: ViewRef) -> dict[str, Any]:
        """One view as its dataset's item: image (3, H, W) float32 linear (learned colour matrix applied),
        mask (1, H, W), K (3, 3) and w2c (4, 4) float64, and the row's metadata."""
        return self.rows[view.dataset_index][view.position]

    def load_batch(
        self, views: list[ViewRef], crop_size: int | None, seed: int, iteration: int, first_sample: int = 0
    ) -> dict[str, torch.Tensor]:
        """Stack views into a batch. With ``crop_size``, the crop of view ``i`` is drawn from the generator of
        global sample ``first_sample + i`` at ``iteration``.

        Returns image (B, 3, H, W), mask and valid (B, 1, H, W), K (B, 3, 3) float32, w2c (B, 4, 4) float32,
        tracked (B, V, 3) (zeros where missing), has_mesh (B,) float, subject_index and dataset_index (B,) int64.
        """
        items = []
        for offset, view in enumerate(views):
            item = self.load_view(view)
            if crop_size is not None:
                rng = iteration_generator(seed, iteration, CROP_STREAM, first_sample + offset)
                item = random_crop(item, crop_size, rng)
            items.append(item)
        shapes = {tuple(item["image"].shape) for item in items}
        if len(shapes) > 1:
            raise InputError(f"views of one batch differ in size {sorted(shapes)}; train with a crop size")
        return {
            **view_batch(items, [self.tracked_vertices(v) for v in views], [v.subject_index for v in views]),
            "dataset_index": torch.tensor([v.dataset_index for v in views], dtype=torch.long),
        }
