"""The synthetic world's answers, brought into the model's image space.

The world (``synth``) writes ``answers/`` next to its native datasets; ingest never reads it, evaluation
does. Answer images are rendered in each dataset's *native* cameras (``<d>/truth.json``: K, OpenCV
distortion, full image) in the world's canonical space, as true scene-linear RGB. The model sees a
normalized row instead: an undistorted crop/resize of the same camera with its own ``K`` and a ``w2c`` in
the normalized canonical space (which may differ from the world's by the ingest's alignment error).

* Pixels: the row image is a 2-D function of the native image (undistort, crop, resize), so the answer is
  warped with ``cv2.initUndistortRectifyMap(K_native, dist, I, K_row)`` at the native resolution and
  area-averaged when the row is smaller than the native image, the filter ingest uses. No 3-D quantity enters the warp.
* Lights: answer lights are given in the world's canonical space. :func:`world_to_normalized` is the rigid
  map between the two canonical spaces, estimated from the cameras both describe (for one subject frame).
* Datasets: the world folder of a normalized dataset (``d1`` .. ``d4``) is the one whose truth cameras are
  the dataset's cameras (:func:`match_world_dataset`), unless given explicitly.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relightanyone.errors import InputError
from relightanyone.render.camera import resize_intrinsics
from relightanyone.render.envmap import load_envmap
from relightanyone.synth.world import render_subject_olat


@dataclass(frozen=True)
class NativeCamera:
    """A world camera as the answers were rendered: K (3, 3), dist (5,) OpenCV, w2c (4, 4), size."""

    name: str
    K: np.ndarray
    dist: np.ndarray
    w2c: np.ndarray
    width: int
    height: int


@dataclass(frozen=True)
class AnswerLights:
    """The D1-rig lights of the OLAT answers: positions (L, 3) world canonical metres, intensities (L, 3)."""

    positions: np.ndarray
    intensities: np.ndarray
    rig_indices: list[int]


class WorldAnswers:
    """Read access to ``<world>/answers`` (splits, cameras, answer lights, OLAT and env-map answers)."""

    def __init__(self, world: str | Path) -> None:
        self.world = Path(world)
        self.root = self.world / "answers"
        if not (self.root / "splits.json").is_file():
            raise FileNotFoundError(
                f"{self.root / 'splits.json'}: not a synthetic world with answers "
                "(generate one with `relightanyone synth world`)"
            )
        self.splits: dict[str, dict[str, str]] = json.loads((self.root / "splits.json").read_text())
        self._cameras: dict[str, dict[str, NativeCamera]] = {}
        self._poses: dict[str, dict[tuple[str, int], np.ndarray]] = {}
        self._rendered: dict[tuple[str, str, str], np.ndarray] = {}

    @property
    def datasets(self) -> list[str]:
        return sorted(self.splits)

    def subjects_in(self, dataset: str, split: str) -> list[str]:
        """Subjects of a world dataset in one split (``answers/splits.json``): train, val or test."""
        if dataset not in self.splits:
            raise InputError(f"{self.root / 'splits.json'}: no dataset {dataset!r}; it has {self.datasets}")
        return sorted(s for s, role in self.splits[dataset].items() if role == split)

    def cameras(self, dataset: str) -> dict[str, NativeCamera]:
        """Native cameras of a world dataset (``answers/<dataset>/truth.json``)."""
        if dataset not in self._cameras:
            path = self.root / dataset / "truth.json"
            if not path.is_file():
                raise FileNotFoundError(f"{path}: truth file of world dataset {dataset!r} is missing")
            data = json.loads(path.read_text())
            try:
                self._cameras[dataset] = {
                    name: NativeCamera(
                        name,
                        np.asarray(c["K"], dtype=np.float64),
                        np.asarray(c["dist"], dtype=np.float64),
                        np.asarray(c["w2c"], dtype=np.float64),
                        int(c["width"]),
                        int(c["height"]),
                    )
                    for name, c in data["cameras"].items()
                }
            except KeyError as error:
                raise InputError(f"{path}: camera entry lacks field {error}") from error
        return self._cameras[dataset]

    def head_pose(self, dataset: str, subject: str, frame: int) -> np.ndarray:
        """(4, 4) head motion of a subject's frame in world canonical space (identity when not recorded)."""
        if dataset not in self._poses:
            data = json.loads((self.root / dataset / "truth.json").read_text())
            self._poses[dataset] = {
                (e["subject"], int(e["frame"])): np.asarray(e["pose"], dtype=np.float64)
                for e in data.get("head_poses", [])
            }
        return self._poses[dataset].get((subject, int(frame)), np.eye(4))

    def answer_lights(self) -> AnswerLights:
        path = self.root / "answer_lights.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: the world has no OLAT answer lights")
        data = json.loads(path.read_text())
        return AnswerLights(
            np.asarray(data["positions"], dtype=np.float64).reshape(-1, 3),
            np.asarray(data["intensities"], dtype=np.float64).reshape(-1, 3),
            [int(i) for i in data.get("rig_indices", [])],
        )

    def envmap_names(self) -> list[str]:
        return sorted(p.stem for p in (self.root / "envmaps").glob("*.exr"))

    def envmap_path(self, name: str) -> Path:
        path = self.root / "envmaps" / f"{name}.exr"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: environment map {name!r} is not among the answers")
        return path

    def olat_path(self, dataset: str, subject: str, camera: str, light: int) -> Path:
        return self.root / dataset / "olat" / subject / camera / f"{light:03d}.exr"

    def olat_image(self, dataset: str, subject: str, camera: str, light: int) -> np.ndarray:
        """(H, W, 3) true image of a subject under answer light ``light`` in a native camera.

        Held-out subjects' images are read from the answers; any other subject's (the stage-1 training
        subjects of the lighting-code ablation) are rendered from the world's seed once per
        (subject, camera) and kept.
        """
        path = self.olat_path(dataset, subject, camera, light)
        if path.is_file():
            return read_answer_image(path)
        key = (dataset, subject, camera)
        if key not in self._rendered:
            self._rendered[key] = render_subject_olat(self.world, dataset, subject, [camera])[camera]
        return self._rendered[key][light]

    def relit_path(self, dataset: str, subject: str, camera: str, envmap: str) -> Path:
        return self.root / dataset / "relit" / subject / camera / f"{envmap}.exr"


def read_answer_image(path: Path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an answer EXR."""

    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: answer image missing (was the world generated with answers?)")
    return load_envmap(path).permute(1, 2, 0).numpy()


def warp_native_to_row(
    image: np.ndarray,
    K_native: np.ndarray,
    dist: np.ndarray,
    K_row: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """Resample a native image (H, W, C) into a normalized row's pinhole crop -> (height, width, C).

    The same filter as ingest's :func:`~relightanyone.ingest.steps.undistort_crop_resize`: when the row
    is coarser than the native image (``s = fx_native / fx_row > 1``), each pixel of the crop at the
    native resolution (``round(s · width)`` wide, the row's aspect kept) looks up the native pixel its ray hits
    (distortion applied, bilinear), then ``cv2.INTER_AREA`` averages every row pixel's footprint; else
    the row's own pixels look up the native image directly. Pixels outside the native image are 0.
    """
    import cv2

    image = np.asarray(image, dtype=np.float32)
    scale = float(K_native[0, 0]) / float(K_row[0, 0])
    fine_width, fine_height, fine_K = width, height, np.asarray(K_row, dtype=np.float64)
    if scale > 1.0 + 1e-6:
        fine_width = round(width * scale)
        ratio = fine_width / width  # one ratio for both axes: rows are square crops
        fine_height = round(height * ratio)
        fine_K = resize_intrinsics(K_row, ratio, ratio)
    map_x, map_y = cv2.initUndistortRectifyMap(
        np.asarray(K_native, dtype=np.float64),
        np.asarray(dist, dtype=np.float64),
        np.eye(3),
        fine_K,
        (fine_width, fine_height),
        cv2.CV_32FC1,
    )
    warped = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if (fine_width, fine_height) != (width, height):
        warped = cv2.resize(warped, (width, height), interpolation=cv2.INTER_AREA)
    if warped.ndim == 2:
        warped = warped[..., None]
    return warped.astype(np.float32)


def world_to_normalized(
    pairs: list[tuple[np.ndarray, np.ndarray]], head_pose: np.ndarray | None = None
) -> np.ndarray:
    """Rigid 4×4 map A from world canonical to normalized canonical points, from (w2c_world, w2c_row) pairs.

    A row folds the frame's head pose P into its camera: ``w2c_row = w2c_world · P · A⁻¹``, so each camera
    gives ``inv(w2c_row) · w2c_world = A · P⁻¹``; rotations are averaged by the SVD projection of their
    sum, translations by their mean, and P (world truth, identity when None) is multiplied back.
    The answers' camera in the normalized space is then ``w2c_world · A⁻¹``.
    """
    if not pairs:
        raise ValueError("world_to_normalized needs at least one camera seen in both spaces")
    maps = np.stack([np.linalg.inv(np.asarray(row)) @ np.asarray(world) for world, row in pairs])
    u, _, vt = np.linalg.svd(maps[:, :3, :3].sum(axis=0))
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = maps[:, :3, 3].mean(axis=0)
    return transform if head_pose is None else transform @ np.asarray(head_pose, dtype=np.float64)


def match_lights(positions: np.ndarray, rig_positions: np.ndarray) -> tuple[list[int], float]:
    """Nearest rig light of each position: (rig indices, largest distance in metres).

    Raises when the match is ambiguous (a distance above a quarter of the rig's smallest light spacing) or
    two positions pick the same rig light.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    rig_positions = np.asarray(rig_positions, dtype=np.float64).reshape(-1, 3)
    distances = np.linalg.norm(positions[:, None] - rig_positions[None], axis=-1)
    nearest = distances.argmin(axis=1)
    worst = float(distances[np.arange(len(positions)), nearest].max())
    spacing = np.linalg.norm(rig_positions[:, None] - rig_positions[None], axis=-1)
    spacing[np.diag_indices_from(spacing)] = np.inf
    tolerance = 0.25 * float(spacing.min()) if len(rig_positions) > 1 else np.inf
    if worst > tolerance or len(set(nearest.tolist())) != len(nearest):
        raise InputError(
            f"answer lights do not match the model's OLAT rig (largest distance {worst:.3f} m, tolerance "
            f"{tolerance:.3f} m); is the stage-2 run trained on this world's D1 dataset?"
        )
    return nearest.tolist(), worst


def match_world_dataset(answers: WorldAnswers, camera_names: set[str], source: str) -> str:
    """The world dataset whose truth cameras include every camera of a normalized dataset."""
    found = [d for d in answers.datasets if camera_names <= set(answers.cameras(d))]
    if len(found) != 1:
        raise InputError(
            f"{source}: cannot tell which world dataset it was ingested from (cameras "
            f"{sorted(camera_names)[:4]}... match {found or 'none'} of {answers.datasets}); "
            "name it explicitly as --data d1=DIR"
        )
    return found[0]
