"""Custom captures -> a :class:`DatasetPlan`: any multi-view rig with OpenCV calibration and tracked meshes.

Layout (``docs/ingest.md``, "Custom captures")::

    cameras.json                                   calibration, units and image encoding (below)
    images/{subject}/{frame}/{camera}.{ext}        ext: exr (linear), png, jpg/jpeg, avif
    alpha/{subject}/{frame}/{camera}.{ext}         optional foreground maps (png, jpg, avif or exr)
    meshes/{subject}/{frame}.obj                   tracked mesh of that frame, template topology,
                                                   in the cameras' world and units

``frame`` folders and mesh names are integers (leading zeros allowed). ``cameras.json``::

    {"units": "m" | "mm" | "cm",                  world and translation units, also of the meshes
     "encoding": "srgb" | "linear",               how 8/16-bit images hold colour (EXR is always linear)
     "cameras": {"<camera>": {"K": 3x3, "dist": [k1, k2, p1, p2, k3] (optional),
                              "w2c": 4x4 or 3x4 world-to-camera (OpenCV axes),
                              "width": W, "height": H}},
     "colour_matrices": {"<camera>": 3x3}         optional linear correction, rgb_out = M @ rgb
     "name": "...", "licence": "..."}             optional

Every problem names the file and the key or camera. An image of a camera absent from ``cameras.json`` is
refused (quarantined), as is a frame without a mesh and an image whose header gives another size than
its camera's ``width``/``height`` (headers are read while planning, so a dry run reports the sizes).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from relightanyone.align.colour import colour_matrix_problem
from relightanyone.format.schema import check_name
from relightanyone.ingest.calibration import loads_json
from relightanyone.ingest.decode import header_size
from relightanyone.ingest.records import (
    AdapterOptions,
    ColourCalibration,
    DatasetPlan,
    ImageRef,
    LayoutError,
    NativeCamera,
    Refusal,
    SourceView,
    SubjectPlan,
)

NAME = "custom"
KIND = "flat"
SOURCE_DATASET = "custom capture"
LICENCE = "as stated by the capture's owner"
CAMERAS_FILE = "cameras.json"
UNITS_TO_M = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
IMAGE_EXTENSIONS = {".exr": "exr", ".png": "png", ".jpg": "jpg", ".jpeg": "jpg", ".avif": "avif"}
_INTEGER = re.compile(r"^\d+$")


def _codec(extension: str, encoding: str) -> str:
    kind = IMAGE_EXTENSIONS[extension]
    if kind == "exr":
        return "exr-linear"
    if kind == "jpg":
        return "jpg-srgb"
    return f"{kind}-{'srgb' if encoding == 'srgb' else 'linear'}"


def _matrix(value, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise LayoutError(f"{where} must be a {'x'.join(map(str, shape))} matrix of numbers") from None
    if array.shape != shape:
        raise LayoutError(f"{where} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise LayoutError(f"{where} holds NaN or infinite values")
    return array


def read_cameras_json(path: Path) -> tuple[dict[str, NativeCamera], dict, float]:
    """Parse ``cameras.json``: ``({name: NativeCamera in metres}, document, units_to_m)``.

    Raises :class:`LayoutError` naming the file, the camera and the key that is missing or wrong.
    """
    if not path.is_file():
        raise LayoutError(f"{path} is missing: a custom capture needs cameras.json (see docs/ingest.md)")
    try:
        document = loads_json(path.read_text())
    except json.JSONDecodeError as error:
        raise LayoutError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(document, dict):
        raise LayoutError(f"{path}: expected a JSON object with 'units' and 'cameras'")
    for key in ("units", "cameras"):
        if key not in document:
            raise LayoutError(f"{path}: missing key {key!r}")
    units = document["units"]
    if units not in UNITS_TO_M:
        raise LayoutError(f"{path}: 'units' must be one of {sorted(UNITS_TO_M)}, got {units!r}")
    encoding = document.get("encoding", "srgb")
    if encoding not in ("srgb", "linear"):
        raise LayoutError(f"{path}: 'encoding' must be 'srgb' or 'linear', got {encoding!r}")
    if not isinstance(document["cameras"], dict) or not document["cameras"]:
        raise LayoutError(f"{path}: 'cameras' must be a non-empty object of camera name -> calibration")
    scale = UNITS_TO_M[units]
    cameras = {}
    for name, entry in sorted(document["cameras"].items()):
        where = f"{path}: camera {name!r}"
        if not isinstance(entry, dict):
            raise LayoutError(f"{where} must be an object")
        for key in ("K", "w2c", "width", "height"):
            if key not in entry:
                raise LayoutError(f"{where}: missing key {key!r}")
        K = _matrix(entry["K"], (3, 3), f"{where} key 'K'")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise LayoutError(f"{where} key 'K': focal lengths must be positive and the last row 0 0 1")
        w2c = np.asarray(entry["w2c"], dtype=np.float64)
        w2c = _matrix(
            np.vstack([w2c, [0, 0, 0, 1]]) if w2c.shape == (3, 4) else w2c, (4, 4), f"{where} key 'w2c'"
        )
        R = w2c[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
            raise LayoutError(
                f"{where} key 'w2c': the rotation is not orthonormal and right-handed (singular?)"
            )
        w2c[:3, 3] *= scale
        dist = np.asarray(entry.get("dist", [0.0] * 5), dtype=np.float64).reshape(-1)
        if dist.size not in (4, 5, 8) or not np.all(np.isfinite(dist)):
            raise LayoutError(f"{where} key 'dist': expected 4, 5 or 8 finite OpenCV coefficients")
        width, height = int(entry["width"]), int(entry["height"])
        if width <= 0 or height <= 0:
            raise LayoutError(f"{where}: 'width' and 'height' must be positive")
        cameras[name] = NativeCamera(
            name=name, K=K, w2c=w2c, dist=np.pad(dist, (0, max(0, 5 - dist.size))), width=width, height=height
        )
    return cameras, document, scale


def _colour(document: dict, camera: str, path: Path) -> ColourCalibration:
    matrices = document.get("colour_matrices") or {}
    if camera not in matrices:
        return ColourCalibration.identity()
    where = f"{path}: colour_matrices[{camera!r}]"
    M = _matrix(matrices[camera], (3, 3), where)
    problem = colour_matrix_problem(M)
    if problem is not None:
        raise LayoutError(f"{where}: {problem}")
    return ColourCalibration(matrix=M, source=f"{CAMERAS_FILE}#colour_matrices/{camera}")


def _frame_dirs(folder: Path) -> list[tuple[int, Path]]:
    return sorted((int(p.name), p) for p in folder.iterdir() if p.is_dir() and _INTEGER.match(p.name))


def detect(src: Path) -> str:
    """``"v1"`` when ``src`` has ``cameras.json``, ``images/`` and ``meshes/``; raises naming what is missing."""
    src = Path(src)
    missing = [name for name in (CAMERAS_FILE, "images", "meshes") if not (src / name).exists()]
    if missing:
        raise LayoutError(f"{src} is not a custom capture: missing {', '.join(missing)} (see docs/ingest.md)")
    return "v1"


def _find_alpha(root: Path, subject: str, frame_dir: str, camera: str) -> Path | None:
    folder = root / "alpha" / subject / frame_dir
    for extension in IMAGE_EXTENSIONS:
        candidate = folder / f"{camera}{extension}"
        if candidate.is_file():
            return candidate
    return None


def _mesh_paths(root: Path, subject: str) -> dict[int, str]:
    folder = root / "meshes" / subject
    if not folder.is_dir():
        return {}
    return {int(p.stem): str(p) for p in sorted(folder.glob("*.obj")) if _INTEGER.match(p.stem)}


def plan(src: Path, options: AdapterOptions | None = None) -> DatasetPlan:
    """Describe every image of a custom capture (no pixel decoded)."""
    options = options or AdapterOptions()
    src = Path(src).resolve()
    version = detect(src)
    cameras_path = src / CAMERAS_FILE
    cameras, document, scale = read_cameras_json(cameras_path)
    encoding = document.get("encoding", "srgb")
    subjects: list[SubjectPlan] = []
    subject_dirs = sorted(p for p in (src / "images").iterdir() if p.is_dir())
    if not subject_dirs:
        raise LayoutError(
            f"{src / 'images'} has no subject folders (expected images/<subject>/<frame>/<camera>.<ext>)"
        )
    for subject_dir in subject_dirs:
        subject = check_name(subject_dir.name, "subject", str(subject_dir))
        if not options.keeps_subject(subject):
            continue
        meshes = _mesh_paths(src, subject)
        views, refusals = [], []
        for frame, frame_dir in _frame_dirs(subject_dir):
            if not options.keeps_frame(frame):
                continue
            for image_path in sorted(frame_dir.iterdir()):
                extension = image_path.suffix.lower()
                if extension not in IMAGE_EXTENSIONS:
                    continue
                camera = image_path.stem
                relative = str(image_path.relative_to(src))
                item = f"{subject}/{frame:06d}/{camera}/full"
                if not options.keeps_camera(camera):
                    continue
                if camera not in cameras:
                    refusals.append(Refusal(item, relative, f"camera {camera!r} is not in {cameras_path}"))
                    continue
                if frame not in meshes:
                    refusals.append(
                        Refusal(
                            item, relative, f"no tracked mesh for frame {frame} in {src / 'meshes' / subject}"
                        )
                    )
                    continue
                codec = _codec(extension, encoding)
                size = header_size(image_path, codec)
                expected = (cameras[camera].width, cameras[camera].height)
                if size is None and image_path.stat().st_size == 0:
                    # Refused here, so that a dry run lists it too; a damaged file is left to the decoder,
                    # whose reason is precise.
                    refusals.append(Refusal(item, relative, f"{image_path.name}: the file is empty"))
                    continue
                if size is not None and size != expected:
                    refusals.append(
                        Refusal(
                            item,
                            relative,
                            f"image is {size[0]}x{size[1]} but {cameras_path.name} gives camera {camera} "
                            f"{expected[0]}x{expected[1]}",
                        )
                    )
                    continue
                alpha = _find_alpha(src, subject, frame_dir.name, camera)
                views.append(
                    SourceView(
                        subject=subject,
                        frame=frame,
                        camera=cameras[camera],
                        pattern="full",
                        image=ImageRef(relative, codec),
                        colour=_colour(document, camera, cameras_path),
                        source=relative,
                        alpha=None
                        if alpha is None
                        else ImageRef(str(alpha.relative_to(src)), _codec(alpha.suffix.lower(), "linear")),
                    )
                )
        subjects.append(
            SubjectPlan(
                subject,
                options.split_of(subject),
                views,
                refusals,
                meshes={f: meshes[f] for f in sorted({v.frame for v in views})},
            )
        )
    if not subjects:
        raise LayoutError(f"{src / 'images'}: none of the selected subjects is there")
    return DatasetPlan(
        dataset=options.dataset_name or document.get("name", NAME),
        kind=KIND,
        layout=NAME,
        layout_version=version,
        source_root=str(src),
        source_dataset=document.get("source", SOURCE_DATASET),
        licence=document.get("licence", LICENCE),
        subjects=subjects,
        found={
            "cameras": sorted({v.camera.name for s in subjects for v in s.views}),
            "units": document["units"],
            "encoding": encoding,
        },
        mesh_units_to_m=scale,
    )
