"""What every ingest adapter produces: one output type for all native layouts.

An adapter reads a native dataset's calibration, colour and file layout and describes each image it
finds as a :class:`SourceView` — where the bytes are, how to decode them, the camera in the dataset's own
world (already converted to OpenCV axes and metres), and the colour calibration to apply. It does not
decode pixels: the shared steps in :mod:`relightanyone.ingest.runner` do that per subject, in worker
processes, so everything here is small and picklable.

The conversion from each native convention happens once, inside its adapter (``docs/conventions.md``);
the shared steps only see these records.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relightanyone.errors import InputError

# How the bytes of an ImageRef are turned into linear float RGB (H, W, 3), before colour calibration.
CODECS = (
    "exr-linear",  # OpenEXR float/half, scene-linear
    "avif-srgb",  # 8-bit display-encoded with the sRGB transfer function
    "avif-linear",  # 8-bit codes holding linear values scaled to [0, 1] (Ava-256 / Goliath releases)
    "avif-gamma22",  # 8-bit display-encoded with a pure 2.2 gamma (FaceOLAT AVIF export)
    "png-srgb",  # 8- or 16-bit PNG, sRGB-encoded
    "jpg-srgb",  # JPEG, sRGB-encoded
    "png-linear",  # 16-bit PNG holding linear values scaled to [0, 1]
    "dng-raw",  # Bayer RAW, demosaiced to linear camera RGB
    "mp4-frame",  # one frame of a video, sRGB-encoded
)


class LayoutError(InputError):
    """A native dataset folder does not have the layout an adapter reads; the message names what is missing."""


@dataclass(frozen=True)
class ImageRef:
    """Where one native image lives.

    ``path`` is a file; ``member`` names an entry inside it when it is a zip archive; ``frame_index`` picks
    a frame when it is a video.
    """

    path: str
    codec: str
    member: str | None = None
    frame_index: int | None = None

    def __post_init__(self) -> None:
        if self.codec not in CODECS:
            raise ValueError(f"unknown codec {self.codec!r} for {self.path}; expected one of {CODECS}")

    @property
    def label(self) -> str:
        """Human-readable location, used as provenance and in error messages."""
        if self.member is not None:
            return f"{self.path}::{self.member}"
        if self.frame_index is not None:
            return f"{self.path}#frame={self.frame_index}"
        return self.path


@dataclass(frozen=True)
class ColourCalibration:
    """A colour correction ``rgb_out = matrix @ (rgb_in - black) + offset``.

    ``space`` says where it applies: ``"linear"`` (scene-linear values, the usual case) or ``"display"``
    (sRGB-encoded values, NeRSemble v1's affine), in which case the shared steps encode, correct and
    decode again.
    """

    matrix: np.ndarray  # (3, 3)
    black: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) subtracted first
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) added last
    space: str = "linear"
    source: str = "identity"  # file or method it came from

    def __post_init__(self) -> None:
        matrix = np.asarray(self.matrix, dtype=np.float64)
        if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
            raise ValueError(f"colour matrix from {self.source} must be a finite 3x3, got {matrix.shape}")
        if self.space not in ("linear", "display"):
            raise ValueError(f"colour calibration space must be 'linear' or 'display', got {self.space!r}")

    def applied_matrix(self) -> np.ndarray:
        """(3, 4) ``[matrix | offset − matrix @ black]``: the same correction as one affine map,
        ``rgb_out = A[:, :3] @ rgb_in + A[:, 3]`` (on display-encoded values when ``space`` is
        ``"display"``), as a row records it."""
        matrix = np.asarray(self.matrix, dtype=np.float64)
        offset = np.asarray(self.offset, dtype=np.float64) - matrix @ np.asarray(self.black, dtype=np.float64)
        return np.hstack([matrix, offset.reshape(3, 1)])

    @staticmethod
    def identity() -> ColourCalibration:
        return ColourCalibration(matrix=np.eye(3))


@dataclass(frozen=True)
class NativeCamera:
    """One camera of one view in the dataset's own world, OpenCV axes, metres, native image pixels."""

    name: str
    K: np.ndarray  # (3, 3)
    w2c: (
        np.ndarray
    )  # (4, 4) native world (metres) -> camera; head pose already folded in where the format has one
    dist: np.ndarray  # (5,) OpenCV k1, k2, p1, p2, k3
    width: int
    height: int


@dataclass(frozen=True)
class SourceView:
    """One native image and everything needed to normalize it."""

    subject: str
    frame: int
    camera: NativeCamera
    pattern: str  # "full", "olat-017", ...
    image: ImageRef
    colour: ColourCalibration
    source: str  # path inside the native dataset (relative to its root), recorded in every row
    alpha: ImageRef | None = None  # optional alpha/foreground map of the same size


@dataclass(frozen=True)
class Refusal:
    """An input item the adapter refused while planning (goes to quarantine.jsonl)."""

    item: str
    source: str
    reason: str


@dataclass
class SubjectPlan:
    """All views of one subject: the unit of work of an ingest run."""

    subject: str
    split: str
    views: list[SourceView]
    refusals: list[Refusal] = field(default_factory=list)
    # Tracked meshes shipped with the dataset itself (custom captures): frame -> OBJ path, in the native
    # world and its units (see DatasetPlan.mesh_units_to_m). Empty when a tracking export provides them.
    meshes: dict[int, str] = field(default_factory=dict)
    # Every calibrated camera of the rig, native ``w2c (4, 4)`` by name, whatever the selection keeps or
    # a dropped frame lacks: the native->tracker fit of each frame uses them all. Empty: the views' cameras.
    rig_w2c: dict[str, np.ndarray] = field(default_factory=dict)
    # frame -> head-to-native-world pose ``(4, 4)`` folded into ``rig_w2c`` for that frame (Ava-256).
    head_poses: dict[int, np.ndarray] = field(default_factory=dict)
    # Facts about this subject printed before writing (image sizes, downscale, ...).
    found: dict = field(default_factory=dict)
    # The capture's native frame rate (fps) and frame count, where a container states them (videos): the
    # tracking's timesteps are paired with native frames against them. None for captures of still images.
    frame_rate: float | None = None
    frame_count: int | None = None


@dataclass
class DatasetPlan:
    """What an adapter found in a native dataset, before any pixel is decoded."""

    dataset: str  # name of the normalized dataset to write
    kind: str  # "olat" | "flat"
    layout: str  # adapter name, e.g. "faceolat"
    layout_version: str  # detected version, e.g. "v2"
    source_root: str
    source_dataset: str  # e.g. "FaceOLAT", "Ava-256"
    licence: str  # licence or access terms of the source
    subjects: list[SubjectPlan]
    # OLAT datasets: the rig in the dataset's world (metres) and linear RGB intensities, pattern names.
    light_positions: np.ndarray | None = None  # (L, 3)
    light_intensities: np.ndarray | None = None  # (L, 3) in each light's OLAT pattern
    full_on_light_intensities: np.ndarray | None = None  # (L, 3) in the full-on pattern, when it differs
    refusals: list[Refusal] = field(default_factory=list)
    found: dict = field(default_factory=dict)  # facts printed before writing (cameras, frames, ...)
    mesh_units_to_m: float = 1.0  # scale of SubjectPlan.meshes coordinates to metres

    @property
    def view_count(self) -> int:
        return sum(len(s.views) for s in self.subjects)


@dataclass(frozen=True)
class AdapterOptions:
    """Selections a user passes on the command line; ``None`` keeps everything."""

    dataset_name: str | None = None  # name of the normalized dataset (default: the adapter's)
    subjects: tuple[str, ...] | None = None
    cameras: tuple[str, ...] | None = None
    frames: tuple[int, ...] | None = None
    test_subjects: tuple[str, ...] = ()  # subjects written with split "test" (all others "train")
    val_subjects: tuple[str, ...] = ()  # subjects written with split "val" (model selection, never trained)
    all_frames: bool = (
        False  # datasets with a preferred frame (Ava-256's neutral peak): take every listed frame
    )
    sequence: str | None = None  # datasets recorded as named sequences (NeRSemble): which one to ingest
    # (width, height) of the sensor the calibration's K describes, when the layout does not say it and it
    # is not the dataset's usual sensor (Ava-256: 2668x4096; NeRSemble: the file's width/height or 2200x3208)
    sensor_size: tuple[int, int] | None = None
    # Names the adapter asked about ("subjects"/"cameras" -> names), so a selection that matches nothing
    # can be named (:meth:`unmatched`).
    asked: dict = field(default_factory=dict, compare=False, repr=False, hash=False)

    def keeps_subject(self, subject: str) -> bool:
        self.asked.setdefault("subjects", set()).add(subject)
        return self.subjects is None or subject in self.subjects

    def keeps_camera(self, camera: str) -> bool:
        self.asked.setdefault("cameras", set()).add(camera)
        return self.cameras is None or camera in self.cameras

    def unmatched(self) -> list[str]:
        """After planning: one line per ``--subjects``/``--cameras`` name the capture does not have, with
        the names it has."""
        lines = []
        for flag, selected in (("subjects", self.subjects), ("cameras", self.cameras)):
            known = self.asked.get(flag, set())
            missing = sorted(set(selected or ()) - known)
            if missing and known:
                names = sorted(known)
                listed = ", ".join(names[:12]) + (f" … and {len(names) - 12} more" if len(names) > 12 else "")
                lines.append(f"--{flag}: {', '.join(missing)} not in the capture (it has {listed})")
        return lines

    def keeps_frame(self, frame: int) -> bool:
        return self.frames is None or frame in self.frames

    def split_of(self, subject: str) -> str:
        if subject in self.test_subjects:
            return "test"
        return "val" if subject in self.val_subjects else "train"


SPLIT_NAMES = ("train", "val", "test")


def published_splits(path: Path) -> dict[str, str]:
    """A published protocol file, JSON ``{"subject": "train" | "val" | "test"}`` -> {subject: split}.

    Subjects it does not list are training subjects; each split value must be one of :data:`SPLIT_NAMES`.
    """
    try:
        splits = json.loads(Path(path).read_text())
    except ValueError as error:
        raise InputError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(splits, dict):
        raise InputError(f'{path}: expected a JSON object {{"subject": "train" | "val" | "test"}}')
    unknown = sorted(f"{s}={v!r}" for s, v in splits.items() if v not in SPLIT_NAMES)
    if unknown:
        raise InputError(
            f"{path}: split values must be one of {', '.join(SPLIT_NAMES)}; got {', '.join(unknown[:3])}"
        )
    return dict(splits)
