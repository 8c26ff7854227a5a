"""Agisoft Metashape camera XML (``document version 2.0.0``) for the D1 light stage.

Follows the structure of FaceOLAT's ``calibration/cameras/NNN.xml``: ``<sensors>`` with one adjusted
frame calibration per camera, a ``<components>`` block, ``<cameras>`` with 4x4 camera-to-chunk
transforms, the chunk ``<transform>`` (rotation, translation, scale), ``<reference>``, ``<region>``,
``<settings>`` and ``<meta>``.

Conventions written (Metashape's, not OpenCV's):

* ``f`` is fy in pixels, ``b1 = fx - fy``; ``cx``/``cy`` are offsets of the principal point from the
  image centre, and Metashape puts the centre of the top-left pixel at (0.5, 0.5), so
  ``cx_opencv = width / 2 + cx - 0.5`` (same for y).
* Metashape's ``p1``/``p2`` are OpenCV's ``p2``/``p1`` (the tangential terms are swapped).
* A camera ``<transform>`` maps camera coordinates (OpenCV axes) to the chunk's internal frame and is
  rigid; the chunk transform maps internal coordinates to the world:
  ``X_world = scale * R @ X_internal + t``. So ``world_from_camera = chunk_matrix @ camera_transform``
  up to the chunk scale on the rotation part.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from relightanyone.synth.raytrace import SynthCamera


def _num(x: float) -> str:
    return format(float(x), ".17g")


def _nums(values) -> str:
    return " ".join(_num(v) for v in np.asarray(values, dtype=np.float64).reshape(-1))


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrs) -> ET.Element:
    element = ET.SubElement(parent, tag, {k: str(v) for k, v in attrs.items()})
    if text is not None:
        element.text = text
    return element


def _sub_properties(parent: ET.Element, tag: str, *properties: tuple[str, str]) -> ET.Element:
    """A ``tag`` child of ``parent`` holding one ``<property name= value=/>`` per (name, value)."""
    element = _sub(parent, tag)
    for name, value in properties:
        _sub(element, "property", name=name, value=value)
    return element


def opencv_to_metashape(camera: SynthCamera) -> dict[str, float]:
    """Metashape calibration values (f, cx, cy, b1, k1, k2, k3, p1, p2) of an OpenCV camera without skew."""
    K = np.asarray(camera.K, dtype=np.float64)
    if abs(K[0, 1]) > 1e-9:
        raise ValueError(f"camera {camera.name}: skewed K cannot be written as b1 only")
    k1, k2, p1, p2, k3 = np.asarray(camera.dist, dtype=np.float64)[:5]
    return {
        "f": K[1, 1],
        "cx": K[0, 2] + 0.5 - camera.width / 2.0,
        "cy": K[1, 2] + 0.5 - camera.height / 2.0,
        "b1": K[0, 0] - K[1, 1],
        "k1": k1,
        "k2": k2,
        "k3": k3,
        "p1": p2,  # Metashape P1 multiplies (r^2 + 2x^2) like OpenCV's p2
        "p2": p1,
    }


def _covariance(rng: np.random.Generator, size: int, scales: np.ndarray) -> np.ndarray:
    """A random symmetric positive-definite matrix with standard deviations near ``scales``."""
    a = rng.normal(size=(size, size)) * 0.3 + np.eye(size)
    corr = a @ a.T
    d = np.sqrt(np.diag(corr))
    corr = corr / np.outer(d, d)
    return corr * np.outer(scales, scales)


def metashape_document(
    cameras: list[SynthCamera],
    world_from_canonical: np.ndarray,
    chunk_scale: float,
    chunk_rotation: np.ndarray,
    chunk_translation: np.ndarray,
    region_centre_canonical: np.ndarray,
    rng: np.random.Generator,
) -> str:
    """The XML text of a calibrated rig whose world is ``world_from_canonical`` (4, 4 similarity) space.

    ``cameras`` are in canonical space. The chunk transform (``chunk_scale``, ``chunk_rotation`` (3, 3),
    ``chunk_translation`` (3,)) maps the internal frame the camera transforms live in to that world.
    """
    W = np.asarray(world_from_canonical, dtype=np.float64)
    world_scale = np.cbrt(np.linalg.det(W[:3, :3]))
    world_rotation = W[:3, :3] / world_scale
    Rc = np.asarray(chunk_rotation, dtype=np.float64)
    tc = np.asarray(chunk_translation, dtype=np.float64)

    def internal_from_canonical_point(p):
        world = W[:3, :3] @ p + W[:3, 3]
        return Rc.T @ (world - tc) / chunk_scale

    root = ET.Element("document", version="2.0.0")
    chunk = _sub(root, "chunk", label="Chunk 1", enabled="true")
    sensors = _sub(chunk, "sensors", next_id=len(cameras))
    for index, cam in enumerate(cameras):
        sensor = _sub(sensors, "sensor", id=index, label=cam.name, type="frame")
        _sub(sensor, "resolution", width=cam.width, height=cam.height)
        _sub(sensor, "property", name="layer_index", value="0")
        calibration = _sub(sensor, "calibration", type="frame", **{"class": "adjusted"})
        _sub(calibration, "resolution", width=cam.width, height=cam.height)
        values = opencv_to_metashape(cam)
        for key in ("f", "cx", "cy", "b1", "k1", "k2", "k3", "p1", "p2"):
            _sub(calibration, key, _num(values[key]))
        covariance = _sub(sensor, "covariance")
        _sub(covariance, "params", "f cx cy b1 k1 k2 k3 p1 p2")
        scales = np.array([30.0, 20.0, 20.0, 3.0, 0.03, 3.0, 100.0, 1e-3, 1e-3]) * rng.uniform(0.5, 1.5, 9)
        _sub(covariance, "coeffs", _nums(_covariance(rng, 9, scales)))

    chunk_rotation_text = _nums(Rc)
    components = _sub(chunk, "components", next_id=1, active_id=0)
    component = _sub(components, "component", id=0, label="Component 1")
    transform = _sub(component, "transform")
    _sub(transform, "rotation", chunk_rotation_text, locked="false")
    _sub(transform, "translation", _nums(tc), locked="false")
    _sub(transform, "scale", _num(chunk_scale), locked="false")
    region_centre = internal_from_canonical_point(np.asarray(region_centre_canonical, dtype=np.float64))
    region_size = np.array([0.45, 0.5, 0.4]) * world_scale / chunk_scale
    region = _sub(component, "region")
    _sub(region, "center", _nums(region_centre))
    _sub(region, "size", _nums(region_size))
    _sub(region, "R", chunk_rotation_text)
    partition = _sub(component, "partition")
    _sub(partition, "camera_ids", " ".join(str(i) for i in range(len(cameras))))

    cams = _sub(chunk, "cameras", next_id=len(cameras), next_group_id=0)
    for index, cam in enumerate(cameras):
        element = _sub(cams, "camera", id=index, sensor_id=index, component_id=0, label=cam.name)
        c2w = np.linalg.inv(np.asarray(cam.w2c, dtype=np.float64))
        camera_transform = np.eye(4)
        camera_transform[:3, :3] = Rc.T @ world_rotation @ c2w[:3, :3]
        camera_transform[:3, 3] = internal_from_canonical_point(c2w[:3, 3])
        _sub(element, "transform", _nums(camera_transform))
        if index > 0:  # as in the real files, the reference camera carries no covariance
            _sub(
                element,
                "rotation_covariance",
                _nums(_covariance(rng, 3, np.full(3, 2e-3) * rng.uniform(0.5, 2, 3))),
            )
            _sub(
                element,
                "location_covariance",
                _nums(_covariance(rng, 3, np.full(3, 1e-3) * rng.uniform(0.5, 2, 3))),
            )

    transform = _sub(chunk, "transform")
    _sub(transform, "rotation", chunk_rotation_text, locked="false")
    _sub(transform, "translation", _nums(tc), locked="false")
    _sub(transform, "scale", _num(chunk_scale), locked="false")
    _sub(chunk, "reference", 'LOCAL_CS["Local CS",LOCAL_DATUM["Local Datum",0],UNIT["meters",1]]')
    region = _sub(chunk, "region")
    _sub(region, "center", _nums(region_centre))
    _sub(region, "size", _nums(region_size))
    _sub(region, "R", chunk_rotation_text)
    _sub_properties(
        chunk,
        "settings",
        ("accuracy_tiepoints", "1"),
        ("accuracy_cameras", "10"),
        ("accuracy_cameras_ypr", "10"),
        ("accuracy_markers", "0.0050000000000000001"),
        ("accuracy_scalebars", "0.001"),
        ("accuracy_projections", "0.5"),
    )
    _sub_properties(
        chunk,
        "meta",
        ("AlignCameras/adaptive_fitting", "false"),
        ("AlignCameras/min_image", "2"),
        ("AlignCameras/reset_alignment", "false"),
        ("OptimizeCameras/adaptive_fitting", "false"),
        ("OptimizeCameras/fit_flags", "f cx cy b1 k1 k2 k3 p1 p2"),
    )

    ET.indent(root, space="  ")
    body = ET.tostring(root, encoding="unicode").replace(" />", "/>")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + body + "\n"
