"""Training and held-out views of several normalized datasets for stage 1.

Only full-on rows (``pattern == "full"``) of training subjects (``split == "train"``) are used. Each
subject keeps a few cameras aside (:func:`relightanyone.model.train.sampling.held_out_cameras`) for the
held-out PSNR/SSIM. Subjects are keyed ``<dataset>/<subject>`` (names only need to be unique within a
dataset). Images stream from the memory-mapped shards one row at a time; nothing but the small index
and the tracked meshes is held in memory.

A dataset folder carries its template mesh as ``template.obj``; all datasets trained together must
share one template topology. A learned colour matrix (``colour_alignment.json``, written by the colour
warm-up) is applied on load: ``rgb = M @ rgb``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from relightanyone.align.colour import read_learned_colour_matrix
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import make_mesh_key
from relightanyone.model.train.sampling import (
    CROP_STREAM,
    choose_crop,
    crop_array,
    held_out_cameras,
    iteration_generator,
)
from relightanyone.render.camera import crop_intrinsics
from relightanyone.render.mesh import load_obj

FULL_ON_PATTERN = "full"
TRAIN_SPLIT = "train"
TEMPLATE_NAME = "template.obj"


@dataclass(frozen=True)
class ViewRef:
    """One image row: which dataset, its key, the identity row and the frame of its tracked mesh."""

    dataset_index: int
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
            raise ValueError("no dataset given: pass at least one normalized dataset folder with --data")
        self.dirs = [Path(d) for d in dataset_dirs]
        self.datasets = [NormalizedDataset(d) for d in self.dirs]
        self.names = [ds.name for ds in self.datasets]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"datasets must have distinct names, got {self.names}")
        self.template_path = self._check_templates()
        self.colour_matrices = [self._learned_matrix(d) if apply_learned_colour else None for d in self.dirs]
        self.subjects: list[str] = []
        self.train_views: list[list[ViewRef]] = []
        self.held_out_views: list[list[ViewRef]] = []
        self._meshes: list[dict[str, np.ndarray]] = []
        for index, dataset in enumerate(self.datasets):
            train, held_out = self._split_views(index, dataset, held_out_per_subject)
            if not train:
                raise ValueError(
                    f"{dataset.path}: no full-on training views (rows with pattern 'full' and split 'train')"
                )
            self.train_views.append(train)
            self.held_out_views.append(held_out)
            self._meshes.append(dataset.meshes())

    def _check_templates(self) -> Path:

        paths = [d / TEMPLATE_NAME for d in self.dirs]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise FileNotFoundError(
                f"template mesh missing: {', '.join(missing)}; ingest writes {TEMPLATE_NAME} beside manifest.json "
                "(re-run ingest, or copy the template OBJ of the tracked meshes there)"
            )
        counts = {str(p): len(load_obj(p).vertices) for p in paths}
        if len(set(counts.values())) > 1:
            raise ValueError(
                f"datasets trained together must share one template topology; vertex counts: {counts}"
            )
        return paths[0]

    @staticmethod
    def _learned_matrix(dataset_dir: Path) -> np.ndarray | None:

        return read_learned_colour_matrix(dataset_dir)

    def _split_views(self, dataset_index: int, dataset, held_out_per_subject: int) -> tuple[list, list]:
        table = dataset.index
        columns = {
            name: table.column(name).to_pylist()
            for name in ("key", "subject", "frame", "camera", "pattern", "split")
        }
        rows_by_subject: dict[str, list[int]] = {}
        for position, (pattern, split) in enumerate(zip(columns["pattern"], columns["split"], strict=True)):
            if pattern == FULL_ON_PATTERN and split == TRAIN_SPLIT:
                rows_by_subject.setdefault(columns["subject"][position], []).append(position)
        train: list[ViewRef] = []
        held_out: list[ViewRef] = []
        for subject in sorted(rows_by_subject):
            subject_index = len(self.subjects)
            self.subjects.append(f"{dataset.name}/{subject}")
            positions = rows_by_subject[subject]
            aside = held_out_cameras([columns["camera"][p] for p in positions], held_out_per_subject)
            for position in positions:
                view = ViewRef(
                    dataset_index=dataset_index,
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

    def load_view(self, view: ViewRef) -> dict[str, np.ndarray]:
        """Decode one view: image (3, H, W) float32 linear (learned colour matrix applied), mask (1, H, W),
        K (3, 3), w2c (4, 4)."""
        row, image, mask = self.datasets[view.dataset_index].decoded(view.key)
        matrix = self.colour_matrices[view.dataset_index]
        if matrix is not None:
            image = image @ matrix.T.astype(np.float32)
        return {
            "image": np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32),
            "mask": mask[None].astype(np.float32),
            "K": row.K,
            "w2c": row.w2c,
        }

    def load_batch(
        self, views: list[ViewRef], crop_size: int | None, seed: int, iteration: int, first_sample: int = 0
    ) -> dict[str, torch.Tensor]:
        """Stack views into a batch. With ``crop_size``, the crop of view ``i`` is drawn from the generator of
        global sample ``first_sample + i`` at ``iteration``.

        Returns image (B, 3, H, W), mask (B, 1, H, W), K (B, 3, 3) float32, w2c (B, 4, 4) float32,
        tracked (B, V, 3) (zeros where missing), has_mesh (B,) float, subject_index and dataset_index (B,) int64.
        """
        samples = []
        for offset, view in enumerate(views):
            sample = self.load_view(view)
            if crop_size is not None:
                rng = iteration_generator(seed, iteration, CROP_STREAM, first_sample + offset)
                box = choose_crop(sample["mask"][0], crop_size, rng)
                sample["image"] = crop_array(sample["image"], box)
                sample["mask"] = crop_array(sample["mask"], box)
                sample["K"] = crop_intrinsics(sample["K"], box.x0, box.y0)
            samples.append(sample)
        shapes = {s["image"].shape for s in samples}
        if len(shapes) > 1:
            raise ValueError(f"views of one batch differ in size {sorted(shapes)}; train with a crop size")
        tracked = [self.tracked_vertices(v) for v in views]
        vertex_count = next((t.shape[0] for t in tracked if t is not None), 0)
        return {
            "image": torch.from_numpy(np.stack([s["image"] for s in samples])),
            "mask": torch.from_numpy(np.stack([s["mask"] for s in samples])),
            "K": torch.tensor(np.stack([s["K"] for s in samples]), dtype=torch.float32),
            "w2c": torch.tensor(np.stack([s["w2c"] for s in samples]), dtype=torch.float32),
            "tracked": torch.from_numpy(
                np.stack([t if t is not None else np.zeros((vertex_count, 3), np.float32) for t in tracked])
            ),
            "has_mesh": torch.tensor([float(t is not None) for t in tracked]),
            "subject_index": torch.tensor([v.subject_index for v in views], dtype=torch.long),
            "dataset_index": torch.tensor([v.dataset_index for v in views], dtype=torch.long),
        }
