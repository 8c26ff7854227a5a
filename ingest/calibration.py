"""Readers for every native camera-calibration convention, each returning :class:`Cameras`.

Each reader converts its format once, here, to the toolkit convention (OpenCV axes, world-to-camera, metres,
pixel centres on integers); ``docs/cameras.md`` gives the conversion used for every format. Malformed input
raises :class:`CalibrationError`, which names the file, the field and the problem.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.render.camera import Cameras, resize_intrinsics

# Full-sensor size of the Ava-256 / Goliath rig (width, height); the Ava loaders hard-code it.
AVA_FULL_SENSOR = (2668, 4096)
# Full-resolution NeRSemble frames (width, height).
NERSEMBLE_FULL_SENSOR = (2200, 3208)
# Metres per unit for the length units a calibration file may use.
UNIT_TO_METRES = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
# Rotations stored in text with ~7 significant digits are orthonormal to ~1e-6; anything worse is corrupt.
ROTATION_TOLERANCE = 1e-4
# OpenGL camera axes (x right, y up, z back) -> OpenCV axes (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class CalibrationError(InputError):
    """A calibration file is malformed; the message names the file, the field and what is wrong."""

    def __init__(self, path: str | Path, field: str, problem: str):
        self.path = str(path)
        self.field = field
        self.problem = problem
        super().__init__(f"{self.path}: field '{field}': {problem}")


# ---------------------------------------------------------------------------------------------- checks
def _matrix(value: Any, shape: tuple[int, ...], path: str | Path, field: str) -> np.ndarray:
    """Parse ``value`` as a finite float64 array of ``shape`` or raise CalibrationError."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise CalibrationError(path, field, f"not a numeric array ({error})") from None
    if array.shape != shape:
        raise CalibrationError(path, field, f"expected shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise CalibrationError(path, field, "contains NaN or infinity")
    return array


def _rotation(R: np.ndarray, path: str | Path, field: str) -> np.ndarray:
    """Check that (3, 3) R is a proper rotation and return the nearest exact one (SVD polar factor)."""
    error = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if error > ROTATION_TOLERANCE or det < 0:
        raise CalibrationError(
            path,
            field,
            f"rotation is not orthonormal with det +1 (|R R^T - I| = {error:.3g}, det = {det:.3g})",
        )
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def _intrinsics(value: Any, path: str | Path, field: str, transpose: bool = False) -> np.ndarray:
    """Parse a (3, 3) pinhole K (optionally stored transposed): positive focal lengths, last row (0, 0, 1)."""
    K = _matrix(value, (3, 3), path, field)
    K = K.T if transpose else K
    if np.abs(K[2] - (0.0, 0.0, 1.0)).max() > 1e-5 or K[1, 0] != 0:
        raise CalibrationError(
            path, field, f"not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: {K.tolist()}"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(path, field, f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    return K


def _rigid(
    value: Any, path: str | Path, field: str, shape: tuple[int, int] = (4, 4), transpose: bool = False
) -> np.ndarray:
    """Parse a (4, 4) or (3, 4) rigid transform (optionally stored transposed); return (4, 4), exact rotation."""
    T = _matrix(value, shape, path, field)
    T = T.T if transpose else T
    out = np.eye(4)
    out[:3, :4] = T[:3, :4]
    if T.shape == (4, 4) and np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-5:
        raise CalibrationError(path, field, f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    out[:3, :3] = _rotation(out[:3, :3], path, field)
    return out


def _invert_rigid(T: np.ndarray) -> np.ndarray:
    """Exact inverse ``[R^T, -R^T t]`` of a (4, 4) rigid transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _get(mapping: Mapping[str, Any], key: str, path: str | Path, field: str) -> Any:
    if not isinstance(mapping, Mapping):
        raise CalibrationError(path, field or "<file>", f"expected an object, got {type(mapping).__name__}")
    if key not in mapping:
        raise CalibrationError(path, f"{field}.{key}" if field else key, "missing")
    return mapping[key]


class DuplicateKeyError(json.JSONDecodeError):
    """A JSON object names one key twice (Python's parser would silently keep the last)."""

    def __init__(self, key: str):
        ValueError.__init__(self, f"key {key!r} appears twice in one object (only one can be meant)")
        self.key = key
        self.msg, self.doc, self.pos, self.lineno, self.colno = str(self), "", 0, 0, 0

    def __reduce__(self):  # rebuilt from its key when it crosses a process boundary
        return DuplicateKeyError, (self.key,)


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document: dict[str, Any] = {}
    for key, value in pairs:
        if key in document:
            raise DuplicateKeyError(key)
        document[key] = value
    return document


def loads_json(text: str) -> Any:
    """``json.loads`` that refuses an object naming a key twice (:class:`DuplicateKeyError`, a
    ``json.JSONDecodeError``): two cameras of one name, one of them silently dropped, is a broken file."""
    return json.loads(text, object_pairs_hook=_unique_keys)


def load_json(source: str | Path | Mapping[str, Any], name: str | Path | None = None) -> tuple[Any, str]:
    """Read a JSON file and return it with the name used in errors. ``source`` may also be a document
    already parsed: a dict, or anything when ``name`` gives the file it was read from."""
    if isinstance(source, Mapping) or name is not None:
        return source, str(name) if name is not None else "<dict>"
    path = Path(source)
    try:
        return loads_json(path.read_text()), str(path)
    except FileNotFoundError:
        raise CalibrationError(path, "<file>", "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise CalibrationError(path, "<file>", f"not valid JSON ({error}); is it truncated?") from None


def _units(units: str) -> float:
    if units not in UNIT_TO_METRES:
        raise ValueError(f"units must be one of {sorted(UNIT_TO_METRES)}, got {units!r}")
    return UNIT_TO_METRES[units]


def _cameras(Ks: list, w2cs: list, dists: list, sizes: list, names: list, path: str | Path) -> Cameras:
    if not Ks:
        raise CalibrationError(path, "<file>", "no cameras found")
    longest = max(len(d) for d in dists)
    dists = [np.pad(d, (0, longest - len(d))) for d in dists]
    return Cameras.create(
        torch.tensor(np.stack(Ks)),
        torch.tensor(np.stack(w2cs)),
        [s[0] for s in sizes],
        [s[1] for s in sizes],
        torch.tensor(np.stack(dists)),
        names,
    )


# ---------------------------------------------------------------------------------------------- Ava-256 / Goliath
def read_krt_json(
    path: str | Path, image_size: tuple[int, int] = AVA_FULL_SENSOR, units: str = "mm"
) -> Cameras:
    """Read an Ava-256 / Goliath ``camera_calibration.json`` (``{"KRT": [...]}``).

    ``K`` and the 4x4 ``T`` (world-to-camera) are stored transposed; translations are in ``units``; the 4
    ``RadialAndTangential`` coefficients are OpenCV (k1, k2, p1, p2). ``image_size`` is (width, height) of the
    images K refers to (the full sensor by default). Camera names are the ``cameraId`` strings.
    """
    data, name = load_json(path)
    scale = _units(units)
    entries = _get(data, "KRT", name, "")
    if not isinstance(entries, list):
        raise CalibrationError(name, "KRT", "expected a list of cameras")
    Ks, w2cs, dists, names = [], [], [], []
    for i, entry in enumerate(entries):
        field = f"KRT[{i}]"
        names.append(str(_get(entry, "cameraId", name, field)))
        field = f"KRT[{i}] (cameraId {names[-1]})"
        model = entry.get("projectionModel", "Pinhole")
        if model != "Pinhole":
            raise CalibrationError(
                name, f"{field}.projectionModel", f"only 'Pinhole' is supported, got {model!r}"
            )
        dist_model = entry.get("distortionModel", "RadialAndTangential")
        if dist_model != "RadialAndTangential":
            raise CalibrationError(name, f"{field}.distortionModel", f"unsupported model {dist_model!r}")
        K = _intrinsics(_get(entry, "K", name, field), name, f"{field}.K", transpose=True)
        w2c = _rigid(_get(entry, "T", name, field), name, f"{field}.T", transpose=True)
        w2c[:3, 3] *= scale
        dist = np.atleast_1d(np.asarray(_get(entry, "distortion", name, field), dtype=np.float64))
        if dist.ndim != 1 or dist.size not in (4, 5) or not np.isfinite(dist).all():
            raise CalibrationError(
                name, f"{field}.distortion", f"expected 4 or 5 finite numbers, got {dist.tolist()}"
            )
        Ks.append(K)
        w2cs.append(w2c)
        dists.append(np.pad(dist, (0, 5 - dist.size)))
    return _cameras(Ks, w2cs, dists, [image_size] * len(Ks), names, name)


def read_krt_text(path: str | Path, image_size: tuple[int, int], units: str = "mm") -> Cameras:
    """Read the legacy Ava KRT text file.

    Each block: a camera-id line, 3 lines of K (row-major), 1 line of 5 OpenCV distortion coefficients, 3 lines of
    the 3x4 world-to-camera ``[R|t]`` with t in ``units``, then a blank line. ``image_size`` is (width, height).
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise CalibrationError(path, "<file>", "file not found") from None
    scale = _units(units)
    Ks, w2cs, dists, names = [], [], [], []
    index = 0
    while index < len(lines):
        if not lines[index].strip():
            index += 1
            continue
        block = lines[index : index + 8]
        camera = block[0].strip()
        field = f"camera {camera} (line {index + 1})"
        if len(block) < 8 or any(not line.strip() for line in block[1:]):
            raise CalibrationError(
                path, field, "incomplete block: expected 8 non-empty lines (id, K, dist, [R|t])"
            )

        def numbers(rows: list[str], part: str, shape: tuple[int, ...], field: str = field) -> np.ndarray:
            try:
                values = [float(v) for row in rows for v in row.split()]
            except ValueError as error:
                raise CalibrationError(path, f"{field}.{part}", f"not numeric ({error})") from None
            if len(values) != math.prod(shape):
                raise CalibrationError(
                    path, f"{field}.{part}", f"expected {math.prod(shape)} numbers, got {len(values)}"
                )
            return np.reshape(values, shape)

        Ks.append(_intrinsics(numbers(block[1:4], "K", (3, 3)), path, f"{field}.K"))
        dists.append(_matrix(numbers(block[4:5], "distortion", (5,)), (5,), path, f"{field}.distortion"))
        w2c = _rigid(numbers(block[5:8], "Rt", (3, 4)), path, f"{field}.Rt", shape=(3, 4))
        w2c[:3, 3] *= scale
        w2cs.append(w2c)
        names.append(camera)
        index += 8
    return _cameras(Ks, w2cs, dists, [image_size] * len(Ks), names, path)


# ---------------------------------------------------------------------------------------------- NeRSemble
def from_nersemble_params(
    source: str | Path | Mapping[str, Any], image_size: tuple[int, int] | None = None
) -> Cameras:
    """Read NeRSemble ``camera_params.json``: ``world_2_cam`` per serial (OpenCV, metres) and ``intrinsics``.

    ``intrinsics`` is one 3x3 shared by all cameras (v1/v2) or a dict per serial (benchmark). ``image_size``
    (width, height) defaults to the file's ``width``/``height`` keys, else the full 2200x3208 frame.
    Cameras keep the file's serial order; names are the serials.
    """
    data, name = load_json(source)
    poses = _get(data, "world_2_cam", name, "")
    intrinsics = _get(data, "intrinsics", name, "")
    if not isinstance(poses, Mapping) or not poses:
        raise CalibrationError(name, "world_2_cam", "expected a non-empty object {serial: 4x4}")
    if image_size is None:
        image_size = (
            int(data.get("width", NERSEMBLE_FULL_SENSOR[0])),
            int(data.get("height", NERSEMBLE_FULL_SENSOR[1])),
        )
    shared = None if isinstance(intrinsics, Mapping) else _intrinsics(intrinsics, name, "intrinsics")
    Ks, w2cs, names = [], [], []
    for serial, pose in poses.items():
        names.append(str(serial))
        w2cs.append(_rigid(pose, name, f"world_2_cam.{serial}"))
        if shared is not None:
            Ks.append(shared)
        else:
            Ks.append(
                _intrinsics(_get(intrinsics, str(serial), name, "intrinsics"), name, f"intrinsics.{serial}")
            )
    dists = [np.zeros(5)] * len(Ks)
    return _cameras(Ks, w2cs, dists, [image_size] * len(Ks), names, name)


# ---------------------------------------------------------------------------------------------- VHAP / NeRF
# The per-frame fields that define a camera in a transforms.json (absent ones fall back to the top level).
_CAMERA_FIELDS = (
    "transform_matrix",
    "w",
    "h",
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
)


def from_transforms_json(
    source: str | Path | Mapping[str, Any],
    per: str = "frame",
    vhap_downsample: int | None = None,
    name: str | Path | None = None,
) -> Cameras:
    """Read a VHAP / NeRF ``transforms.json`` (camera-to-world in OpenGL axes, intrinsics per frame or top level).

    ``c2w_cv = transform_matrix @ diag(1, -1, -1, 1)``. VHAP writes ``cy = H - cy_opencv`` (a bottom-origin
    principal point), so ``cy_opencv = h - cy`` with the frame's h; ``cx`` is unchanged. VHAP downscales K with
    no half-pixel term; pass its ``vhap_downsample`` factor n to apply the half-pixel rule, which shifts both
    principal-point coordinates by ``-0.5 * (1 - 1/n)``. Optional ``k1, k2, k3, k4, p1, p2`` become OpenCV
    coefficients. ``per="frame"`` returns one camera per frame (named by ``file_path``); ``per="camera"`` one per
    distinct ``camera_id`` / ``camera_index`` (first frame wins; all frames of a camera must agree).
    ``name``: the file an already-parsed ``source`` was read from, named in errors.
    """
    if per not in ("frame", "camera"):
        raise ValueError(f"per must be 'frame' or 'camera', got {per!r}")
    data, name = load_json(source, name)
    frames = _get(data, "frames", name, "")
    if not isinstance(frames, list) or not frames:
        raise CalibrationError(name, "frames", "expected a non-empty list")
    shift = 0.0 if vhap_downsample is None else -0.5 * (1.0 - 1.0 / vhap_downsample)
    Ks, w2cs, dists, sizes, names, seen = [], [], [], [], [], {}
    # per="camera": a VHAP export repeats every camera once per timestep; an entry whose raw fields equal
    # its camera's first entry is skipped before parsing (thousands of entries per subject).
    raw_seen: dict[str, tuple] = {}
    for i, frame in enumerate(frames):
        field = f"frames[{i}]"
        if isinstance(frame, Mapping):  # anything else is refused below, naming the field
            key = str(frame.get("camera_id", frame.get("camera_index", frame.get("file_path", i))))
            raw = tuple(frame.get(k) for k in _CAMERA_FIELDS)
            if per == "camera" and raw_seen.get(key) == raw:
                continue

        def value(key: str, default: float | None = None, frame: Any = frame, field: str = field) -> float:
            raw = frame.get(key, data.get(key, default)) if isinstance(frame, Mapping) else None
            if raw is None:
                raise CalibrationError(name, f"{field}.{key}", "missing (in the frame and at the top level)")
            return float(_matrix(raw, (), name, f"{field}.{key}"))

        c2w_gl = _rigid(_get(frame, "transform_matrix", name, field), name, f"{field}.transform_matrix")
        w, h = int(value("w")), int(value("h"))
        fl_x = value("fl_x")
        fl_y = value("fl_y", default=fl_x)
        K = np.array(
            [[fl_x, 0.0, value("cx") + shift], [0.0, fl_y, h - value("cy") + shift], [0.0, 0.0, 1.0]]
        )
        _intrinsics(K, name, f"{field}.fl_x/fl_y")
        dist = np.array([value(k, default=0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
        if value("k4", default=0.0) != 0:
            raise CalibrationError(name, f"{field}.k4", "fisheye k4 is not part of the OpenCV pinhole model")
        w2c = _invert_rigid(c2w_gl @ GL_TO_CV)
        if per == "camera":
            if key in seen:
                j = seen[key]
                if not (np.allclose(Ks[j], K) and np.allclose(w2cs[j], w2c, atol=1e-9)):
                    raise CalibrationError(
                        name, field, f"camera {key} has different parameters than in an earlier frame"
                    )
                continue
            seen[key] = len(Ks)
            raw_seen[key] = raw
        names.append(key if per == "camera" else str(frame.get("file_path", i)))
        Ks.append(K)
        w2cs.append(w2c)
        dists.append(dist)
        sizes.append((w, h))
    return _cameras(Ks, w2cs, dists, sizes, names, name)


# ---------------------------------------------------------------------------------------------- COLMAP
def from_colmap(source: str | Path | Any) -> Cameras:
    """Read a COLMAP sparse model (binary or text folder, or a ``pycolmap.Reconstruction``), one camera per
    registered image, named by image name and sorted by it.

    Models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV. COLMAP puts the centre of the
    top-left pixel at (0.5, 0.5), so ``c_ours = c_colmap - 0.5``.
    """
    import pycolmap

    name = str(source) if isinstance(source, str | Path) else "<pycolmap.Reconstruction>"
    if isinstance(source, str | Path):
        if not Path(source).is_dir():
            raise CalibrationError(source, "<folder>", "COLMAP model folder not found")
        try:
            source = pycolmap.Reconstruction(str(source))
        except Exception as error:  # pycolmap raises plain RuntimeError/ValueError on unreadable models
            raise CalibrationError(name, "<model>", f"pycolmap could not read the model ({error})") from None
    Ks, w2cs, dists, sizes, names = [], [], [], [], []
    for image in sorted(source.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        camera = image.camera
        field = f"cameras[{camera.camera_id}] (image {image.name})"
        K, dist = _colmap_intrinsics(
            camera.model.name, np.asarray(camera.params, dtype=np.float64), name, field
        )
        pose = image.cam_from_world()
        w2cs.append(_rigid(pose.matrix(), name, f"images[{image.name}].pose", shape=(3, 4)))
        Ks.append(K)
        dists.append(dist)
        sizes.append((camera.width, camera.height))
        names.append(image.name)
    return _cameras(Ks, w2cs, dists, sizes, names, name)


def _colmap_intrinsics(model: str, p: np.ndarray, path: str, field: str) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP camera model + params -> (3, 3) K (integer pixel centres) and OpenCV coefficients."""
    counts = {
        "SIMPLE_PINHOLE": 3,
        "PINHOLE": 4,
        "SIMPLE_RADIAL": 4,
        "RADIAL": 5,
        "OPENCV": 8,
        "FULL_OPENCV": 12,
    }
    if model not in counts:
        raise CalibrationError(
            path, f"{field}.model", f"unsupported COLMAP model {model}; use one of {sorted(counts)}"
        )
    _matrix(p, (counts[model],), path, f"{field}.params")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    else:
        fx, fy, cx, cy = p[:4]
    dist = np.zeros(8 if model == "FULL_OPENCV" else 5)
    if model == "SIMPLE_RADIAL":
        dist[0] = p[3]
    elif model == "RADIAL":
        dist[:2] = p[3:5]
    elif model == "OPENCV":
        dist[:4] = p[4:8]
    elif model == "FULL_OPENCV":
        dist[:] = p[4:12]  # k1 k2 p1 p2 k3 k4 k5 k6: already OpenCV order
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return _intrinsics(K, path, f"{field}.params"), dist


@dataclass(frozen=True)
class Downscale:
    """How stored images relate to the sensor a calibration describes.

    ``factor`` is the native downscale (sensor / image, an integer when one fits both axes, else the one
    the long axis gives); ``sensor`` and ``image`` are ``(width, height)``.
    """

    factor: float
    sensor: tuple[int, int]
    image: tuple[int, int]

    def intrinsics(self, K_sensor: np.ndarray) -> np.ndarray:
        """``(..., 3, 3)`` K of the stored images: the sensor's K resized to the image size, each axis by its
        exact ratio with the half-pixel rule (the image is the sensor resampled to its stored size)."""
        sx = self.image[0] / self.sensor[0]
        sy = self.image[1] / self.sensor[1]
        return resize_intrinsics(np.asarray(K_sensor, dtype=np.float64), sx, sy)


def _fits(sensor: int, image: int, factor: float) -> bool:
    """Whether ``sensor / factor`` rounds (up or down) to ``image`` pixels."""
    return abs(sensor / factor - image) < 1.0


def downsample_factor(
    K_sensor: np.ndarray,
    image_size: tuple[int, int],
    sensor_size: tuple[int, int],
    option: str = "--sensor-size",
) -> Downscale:
    """The downscale between the calibrated sensor and the stored images, from their sizes.

    K_sensor: (B, 3, 3) the rig's intrinsics in sensor pixels; image_size, sensor_size: (width, height).
    Both axes must give the same downscale within rounding (4096 / 16 = 256 and 2668 / 16 = 166.75, stored
    as 167 or 166), integer or not. The principal points are only a consistency check: their median must
    lie in the middle third of the sensor, which catches a calibration made for another sensor size (the
    message names the size they suggest and ``option`` to pass it). Raises InputError otherwise.
    """
    width, height = (int(v) for v in image_size)
    sensor_w, sensor_h = (int(v) for v in sensor_size)
    sensor_text = f"{sensor_w}x{sensor_h}"
    if width <= 0 or height <= 0:
        raise InputError(f"images are {width}x{height}: no image size to relate to the {sensor_text} sensor")
    ratios = (sensor_w / width, sensor_h / height)
    nearest = round(max(ratios))
    if nearest >= 1 and _fits(sensor_w, width, nearest) and _fits(sensor_h, height, nearest):
        factor = float(nearest)
    else:
        # The long axis has the finer rounding; the other axis must round to its stored size too.
        factor = ratios[0] if width >= height else ratios[1]
        if not (_fits(sensor_w, width, factor) and _fits(sensor_h, height, factor)):
            raise InputError(
                f"images are {width}x{height}, which is no downscale of the {sensor_text} sensor: the width "
                f"gives {ratios[0]:.3f}, the height {ratios[1]:.3f}; if the calibration describes another "
                f"sensor, pass {option} WxH"
            )
    centre = np.median(np.asarray(K_sensor, dtype=np.float64).reshape(-1, 3, 3)[:, :2, 2], axis=0)
    if not _centred(centre, (sensor_w, sensor_h)):
        # Sensors the images are an integer downscale of, whose middle third holds the principal points.
        fitting = [
            (width * k, height * k)
            for k in (1, 2, 3, 4, 6, 8, 16, 32)
            if _centred(centre, (width * k, height * k))
        ]
        if fitting:
            own = (
                " (the images' own size: K is already in their pixels)"
                if fitting[0] == (width, height)
                else ""
            )
            suggestion = f"they fit a sensor of {fitting[0][0]}x{fitting[0][1]}{own}"
        else:
            suggestion = "they fit no integer multiple of the image size"
        raise InputError(
            f"the principal points (median ({centre[0]:.0f}, {centre[1]:.0f}) px) are far from the centre of "
            f"the {sensor_text} sensor the calibration is read for, so its K cannot describe that sensor; "
            f"{suggestion}: pass {option} WxH with the size the calibration was made at"
        )
    return Downscale(factor, (sensor_w, sensor_h), (width, height))


def _centred(centre: np.ndarray, size: tuple[int, int]) -> bool:
    """Whether the principal point ``centre (2,)`` lies in the middle third of a ``size`` (W, H) sensor."""
    extent = np.asarray(size, dtype=np.float64)
    return bool((np.abs(centre - (extent - 1.0) / 2.0) <= extent / 6.0).all())
