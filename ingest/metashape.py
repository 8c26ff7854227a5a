"""Agisoft Metashape camera XML (FaceOLAT / 3DPR calibrations) into :class:`Cameras`.

Sensors carry the intrinsics (``cx``/``cy`` as offsets from the image centre, ``b1`` affinity, k1-k3 and
p1/p2 in Metashape's order), cameras carry camera-to-chunk transforms, and the chunk transform (rotation,
translation, scale) maps the chunk into the world; ``docs/cameras.md`` gives the conversion. Cameras that
cannot be used are reported by label in :attr:`MetashapeRig.missing`, never guessed.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relightanyone.ingest.calibration import (
    CalibrationError,
    _cameras,
    _intrinsics,
    _invert_rigid,
    _matrix,
    _rigid,
    _rotation,
)
from relightanyone.render.camera import Cameras


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
