"""Readers for every native camera-calibration convention, each returning :class:`Cameras`.

Each reader converts its format once, here, to the toolkit convention (OpenCV axes, world-to-camera, metres,
pixel centres on integers); ``docs/cameras.md`` gives the conversion used for every format. Malformed input
raises :class:`CalibrationError`, which names the file, the field and the problem.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .camera import Cameras

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


class CalibrationError(ValueError):
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
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
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
    if T.shape == (4, 4) and not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
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
        raise CalibrationError(path, field, f"expected an object, got {type(mapping).__name__}")
    if key not in mapping:
        raise CalibrationError(path, f"{field}.{key}" if field else key, "missing")
    return mapping[key]


def _load_json(source: str | Path | Mapping[str, Any]) -> tuple[Any, str]:
    """Read a JSON file (or take an already-parsed dict) and return it with the name used in errors."""
    if isinstance(source, Mapping):
        return source, "<dict>"
    path = Path(source)
    try:
        return json.loads(path.read_text()), str(path)
    except FileNotFoundError:
        raise CalibrationError(path, "<file>", "file not found") from None
    except json.JSONDecodeError as error:
        raise CalibrationError(path, "<file>", f"not valid JSON ({error})") from None


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
    data, name = _load_json(path)
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
    data, name = _load_json(source)
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
def from_transforms_json(
    source: str | Path | Mapping[str, Any], per: str = "frame", vhap_downsample: int | None = None
) -> Cameras:
    """Read a VHAP / NeRF ``transforms.json`` (camera-to-world in OpenGL axes, intrinsics per frame or top level).

    ``c2w_cv = transform_matrix @ diag(1, -1, -1, 1)``. VHAP writes ``cy = H - cy_opencv`` (a bottom-origin
    principal point), so ``cy_opencv = h - cy`` with the frame's h; ``cx`` is unchanged. VHAP downscales K with
    no half-pixel term; pass its ``vhap_downsample`` factor n to apply the half-pixel rule, which shifts both
    principal-point coordinates by ``-0.5 * (1 - 1/n)``. Optional ``k1, k2, k3, k4, p1, p2`` become OpenCV
    coefficients. ``per="frame"`` returns one camera per frame (named by ``file_path``); ``per="camera"`` one per
    distinct ``camera_id`` / ``camera_index`` (first frame wins; all frames of a camera must agree).
    """
    if per not in ("frame", "camera"):
        raise ValueError(f"per must be 'frame' or 'camera', got {per!r}")
    data, name = _load_json(source)
    frames = _get(data, "frames", name, "")
    if not isinstance(frames, list) or not frames:
        raise CalibrationError(name, "frames", "expected a non-empty list")
    shift = 0.0 if vhap_downsample is None else -0.5 * (1.0 - 1.0 / vhap_downsample)
    Ks, w2cs, dists, sizes, names, seen = [], [], [], [], [], {}
    for i, frame in enumerate(frames):
        field = f"frames[{i}]"

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
        key = str(frame.get("camera_id", frame.get("camera_index", frame.get("file_path", i))))
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


# ---------------------------------------------------------------------------------------------- Metashape
@dataclass(frozen=True)
class MetashapeRig:
    """Cameras of a Metashape XML and the ones that could not be used.

    Attributes:
        cameras: every camera with calibration and a transform; ``cameras.names`` are the camera labels.
        missing: label -> reason, for every sensor or camera that lacks calibration, a ``<camera>`` element or a
            transform (or uses a model that cannot be represented).
        chunk_scale: the chunk transform's scale (chunk units -> world units).
        metres_per_unit: from the chunk ``<reference>`` (``UNIT[...]`` of a ``LOCAL_CS``), 1 otherwise.
    """

    cameras: Cameras
    missing: dict[str, str]
    chunk_scale: float
    metres_per_unit: float


def _xml_numbers(element: ET.Element | None, count: int, path: Path, field: str) -> np.ndarray:
    if element is None or element.text is None:
        raise CalibrationError(path, field, "missing")
    try:
        values = np.array([float(v) for v in element.text.split()])
    except ValueError as error:
        raise CalibrationError(path, field, f"not numeric ({error})") from None
    if values.size != count:
        raise CalibrationError(path, field, f"expected {count} numbers, got {values.size}")
    return _matrix(values, (count,), path, field)


def _chunk_similarity(transform: ET.Element | None, path: Path, field: str) -> np.ndarray:
    """The 4x4 ``[[s R, t], [0, 1]]`` of a chunk/component ``<transform>`` (identity when absent)."""
    S = np.eye(4)
    if transform is None:
        return S
    rotation = transform.find("rotation")
    R = (
        np.eye(3)
        if rotation is None
        else _rotation(
            _xml_numbers(rotation, 9, path, f"{field}.rotation").reshape(3, 3), path, f"{field}.rotation"
        )
    )
    translation = transform.find("translation")
    t = np.zeros(3) if translation is None else _xml_numbers(translation, 3, path, f"{field}.translation")
    scale_el = transform.find("scale")
    s = 1.0 if scale_el is None else float(_xml_numbers(scale_el, 1, path, f"{field}.scale")[0])
    if s <= 0:
        raise CalibrationError(path, f"{field}.scale", f"must be positive, got {s}")
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


def _metashape_intrinsics(
    sensor: ET.Element, calibration: ET.Element, path: Path, field: str
) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Metashape frame calibration -> OpenCV (K, dist (5,), (width, height)).

    Metashape: ``u = w/2 + cx + x'(f + b1) + y' b2``, ``v = h/2 + cy + y' f`` with the top-left pixel centre at
    (0.5, 0.5), and tangential terms ``x' += P1 (r^2 + 2x^2) + 2 P2 x y`` — OpenCV's p1/p2 swapped.
    """
    resolution = calibration.find("resolution")
    if resolution is None:
        resolution = sensor.find("resolution")
    if resolution is None:
        raise CalibrationError(path, f"{field}.resolution", "missing")
    try:
        width, height = int(resolution.get("width", "")), int(resolution.get("height", ""))
    except ValueError:
        raise CalibrationError(path, f"{field}.resolution", "width/height missing or not integers") from None

    def param(tag: str, required: bool = False) -> float:
        element = calibration.find(tag)
        if element is None:
            if required:
                raise CalibrationError(path, f"{field}.calibration.{tag}", "missing")
            return 0.0
        return float(_xml_numbers(element, 1, path, f"{field}.calibration.{tag}")[0])

    f = param("f", required=True)
    K = np.array(
        [
            [f + param("b1"), param("b2"), width / 2 + param("cx") - 0.5],
            [0.0, f, height / 2 + param("cy") - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array([param("k1"), param("k2"), param("p2"), param("p1"), param("k3")])
    return _intrinsics(K, path, f"{field}.calibration"), dist, (width, height)


def _metres_per_unit(chunk: ET.Element) -> float:
    reference = chunk.find("reference")
    if reference is None or reference.text is None or not reference.text.startswith("LOCAL_CS"):
        return 1.0
    units = re.findall(r'UNIT\["[^"]*",\s*([0-9.eE+-]+)\]', reference.text)
    return float(units[-1]) if units else 1.0


def read_metashape_xml(path: str | Path) -> MetashapeRig:
    """Read an Agisoft Metashape camera XML into world-space cameras plus a report of unusable cameras.

    World = chunk similarity ``S = [[s R, t], [0, 1]]`` applied to the chunk frame, times ``metres_per_unit``;
    each ``<camera><transform>`` is camera-to-chunk in OpenCV axes. A camera's centre is mapped by S, its axes by
    S's rotation only, so every w2c stays rigid in metres. Cameras inside ``<group>`` elements are included; a
    camera's component transform is used when the chunk has none.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise CalibrationError(path, "<file>", "file not found") from None
    except ET.ParseError as error:
        raise CalibrationError(path, "<file>", f"not valid XML ({error})") from None
    chunk = root if root.tag == "chunk" else root.find("chunk")
    if chunk is None:
        raise CalibrationError(path, "document/chunk", "missing")
    sensors_el = chunk.find("sensors")
    cameras_el = chunk.find("cameras")
    if sensors_el is None:
        raise CalibrationError(path, "chunk/sensors", "missing")
    if cameras_el is None:
        raise CalibrationError(path, "chunk/cameras", "missing")
    sensors = {s.get("id"): s for s in sensors_el.iter("sensor")}
    chunk_S = _chunk_similarity(chunk.find("transform"), path, "chunk/transform")
    components = {
        c.get("id"): _chunk_similarity(c.find("transform"), path, f"component[{c.get('id')}]/transform")
        for c in chunk.iter("component")
        if c.find("transform") is not None
    }
    metres = _metres_per_unit(chunk)
    missing: dict[str, str] = {}
    Ks, c2ws, dists, sizes, names = [], [], [], [], []
    used_sensors = set()
    for camera in cameras_el.iter("camera"):
        label = camera.get("label") or f"camera {camera.get('id')}"
        sensor = sensors.get(camera.get("sensor_id"))
        used_sensors.add(camera.get("sensor_id"))
        field = f"camera[{label}]"
        if sensor is None:
            missing[label] = f"its sensor_id {camera.get('sensor_id')} has no <sensor> element"
            continue
        calibrations = sensor.findall("calibration")
        # Metashape may keep the initial guess beside the adjusted result; the adjusted one is the calibration.
        adjusted = [c for c in calibrations if c.get("class") == "adjusted"]
        calibration = (adjusted or calibrations or [None])[0]
        if calibration is None:
            missing[label] = f"sensor {sensor.get('label')} has no <calibration>"
            continue
        if sensor.get("type", "frame") != "frame" or calibration.get("type", "frame") != "frame":
            missing[label] = f"sensor type {sensor.get('type')!r} is not a frame (pinhole) camera"
            continue
        unsupported = [
            tag
            for tag in ("k4", "p3", "p4")
            if calibration.find(tag) is not None
            and _xml_numbers(calibration.find(tag), 1, path, f"{field}/calibration.{tag}")[0] != 0
        ]
        if unsupported:
            missing[label] = (
                f"calibration uses {', '.join(unsupported)}, which the OpenCV model cannot represent"
            )
            continue
        transform = camera.find("transform")
        if transform is None:
            missing[label] = "camera has no <transform> (not aligned)"
            continue
        S = components.get(camera.get("component_id"), chunk_S)
        if chunk.find("transform") is not None and not np.allclose(S, chunk_S):
            missing[label] = (
                f"its component {camera.get('component_id')} has a transform that differs from the chunk's"
            )
            continue
        K, dist, size = _metashape_intrinsics(sensor, calibration, path, f"sensor[{sensor.get('label')}]")
        c2w_chunk = _rigid(
            _xml_numbers(transform, 16, path, f"{field}/transform").reshape(4, 4), path, f"{field}/transform"
        )
        c2ws.append(_similarity_times_rigid(S, c2w_chunk, metres))
        Ks.append(K)
        dists.append(dist)
        sizes.append(size)
        names.append(label)
    for sensor_id, sensor in sensors.items():
        if sensor_id not in used_sensors:
            label = sensor.get("label") or f"sensor {sensor_id}"
            has_calibration = sensor.find("calibration") is not None
            missing[label] = "no <camera> element" + (
                "" if has_calibration else " and sensor has no <calibration>"
            )
    if not Ks:
        raise CalibrationError(path, "chunk/cameras", f"no usable camera; problems: {missing}")
    cameras = _cameras(Ks, [_invert_rigid(c2w) for c2w in c2ws], dists, sizes, names, path)
    scale = float(np.cbrt(np.linalg.det(chunk_S[:3, :3])))
    return MetashapeRig(cameras=cameras, missing=missing, chunk_scale=scale, metres_per_unit=metres)


def _similarity_times_rigid(S: np.ndarray, c2w: np.ndarray, metres: float) -> np.ndarray:
    """World c2w of a camera with chunk c2w ``c2w``: the centre moves by S (then to metres), the axes turn by
    S's rotation only, so the camera stays rigid."""
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    out = np.eye(4)
    out[:3, :3] = (S[:3, :3] / scale) @ c2w[:3, :3]
    out[:3, 3] = metres * (S[:3, :3] @ c2w[:3, 3] + S[:3, 3])
    return out
