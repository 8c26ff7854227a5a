"""``export-dataset``: a normalized dataset as plain files for tools outside this toolkit.

Layout of the export folder::

    <subject>/<frame:06d>/<camera>/<pattern>.exr        linear RGB, OpenEXR (float32 or half, ZIP)
    <subject>/<frame:06d>/<camera>/<pattern>.mask.png   the stored 8-bit mask, 255 = foreground
    <subject>/<frame:06d>/<camera>/<pattern>.valid.png  8-bit, 255 where the pixel came from the source
                                                        image, 0 on the zero padding of a crop past its edge
    cameras.json     one row per image: key, subject, frame, camera, pattern, split, width, height,
                     K (3x3, pixels of the stored image), w2c (4x4, OpenCV, metres), crop,
                     colour_matrix (3x4 affine already applied: rgb = M[:, :3] @ source + M[:, 3]),
                     image, mask and valid file names relative to the export folder
    lights.json      the rig of an OLAT dataset (index, name, position_m, intensity_rgb, pattern); [] if flat
    dataset.json     name, kind, lighting, provenance, conventions, counts (written last: an export
                     without it is incomplete)

The conventions are those of the normalized format (docs/format.md): scene-linear RGB, OpenCV cameras
with the centre of pixel (u, v) at (u, v), canonical head space in metres. Every file is written under a
temporary name and renamed, so an interrupted export never leaves a truncated image; running it again
rewrites the same bytes.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import numpy as np

from relightanyone.errors import RelightAnyoneError
from relightanyone.format.arrow_io import atomic_write_bytes
from relightanyone.format.codecs import encode_mask
from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
from relightanyone.format.schema import INDEX_NAME, MANIFEST_NAME, SchemaError, check_name
from relightanyone.format.shards import dataset_dirs
from relightanyone.locking import output_lock
from relightanyone.os_errors import naming_file
from relightanyone.progress import progress_bar

EXPORT_CONVENTIONS = {
    "colour": "scene-linear RGB after the dataset's colour calibration",
    "camera": "OpenCV pinhole: x right, y down, z forward; K in pixels of the stored image, pixel centres at "
    "integer coordinates",
    "extrinsics": "w2c: 4x4 world-to-camera, row-major, metres, canonical head space (+y up, +z out of the face)",
    "mask": "8-bit PNG, 255 = foreground",
    "valid": "8-bit PNG, 255 = the pixel came from the source image, 0 = zero padding past its edge",
}


class ExportError(RelightAnyoneError, RuntimeError):
    """The dataset cannot be exported; the message names the folder and the problem."""


def encode_exr(image: np.ndarray, precision: str = "float") -> bytes:
    """(H, W, 3) float linear RGB -> OpenEXR bytes (ZIP) with ``precision`` "float" (exact) or "half"."""
    import OpenEXR

    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {image.shape}")
    dtype = {"float": np.float32, "half": np.float16}[precision]
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buffer = io.BytesIO()
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(image.astype(dtype))}).write(buffer)
    return buffer.getvalue()


def read_exr(path: Path) -> np.ndarray:
    """An RGB OpenEXR file -> (H, W, 3) float32."""
    import OpenEXR

    channels = OpenEXR.File(str(path)).channels()
    if "RGB" in channels:
        return np.asarray(channels["RGB"].pixels, dtype=np.float32)
    return np.stack([np.asarray(channels[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)


def _write_file(path: Path, data: bytes) -> None:
    """Temporary name then rename: a reader never sees a truncated file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    with naming_file(temporary):  # a failed write (a full disk) names no file
        temporary.write_bytes(data)
    os.replace(temporary, path)


def image_paths(
    subject: str, frame: int, camera: str, pattern: str, where: str = "image row"
) -> tuple[str, str, str]:
    """Relative (image, mask, valid) file names of one image row in the export folder; ``UnsafeNameError`` naming
    ``where`` when a name is not one safe file name, so no file lands outside the folder."""
    for what, name in (("subject", subject), ("camera", camera), ("pattern", pattern)):
        check_name(name, what, where)
    folder = f"{subject}/{int(frame):06d}/{camera}"
    return f"{folder}/{pattern}.exr", f"{folder}/{pattern}.mask.png", f"{folder}/{pattern}.valid.png"


def camera_entry(row, image_file: str, mask_file: str, valid_file: str) -> dict:
    """The ``cameras.json`` row of an image row (matrices as nested lists)."""
    return {
        "key": row.key,
        "subject": row.subject,
        "frame": int(row.frame),
        "camera": row.camera,
        "pattern": row.pattern,
        "split": row.split,
        "width": int(row.width),
        "height": int(row.height),
        "K": np.asarray(row.K, dtype=np.float64).tolist(),
        "w2c": np.asarray(row.w2c, dtype=np.float64).tolist(),
        "crop": [int(v) for v in row.crop],
        "colour_matrix": np.asarray(row.colour_matrix, dtype=np.float64).tolist(),
        "image": image_file,
        "mask": mask_file,
        "valid": valid_file,
    }


def _open_dataset(path: Path):

    path = Path(path)
    if not (path / MANIFEST_NAME).exists():
        found = dataset_dirs(path)
        names = ", ".join(p.name for p in found)
        hint = (
            f"it holds several datasets ({names}); export them one at a time" if found else "no manifest.json"
        )
        raise ExportError(f"{path}: not a normalized dataset folder ({hint})")
    try:
        return NormalizedDataset(path)
    except (IncompleteDatasetError, SchemaError) as error:
        raise ExportError(str(error)) from None


def export_dataset(
    dataset_dir: Path,
    out: Path,
    precision: str = "float",
    subjects: tuple[str, ...] | None = None,
    progress: bool = True,
) -> dict:
    """Write the dataset at ``dataset_dir`` into ``out`` (layout in the module docstring).

    Returns a summary ``{"dataset", "images", "subjects", "lights"}``. Raises ExportError for a folder that
    is not one complete dataset or for unknown ``subjects``. ``out`` is locked while it is written
    (:mod:`relightanyone.locking`): a second export into it stops with an error naming this one.
    """
    if precision not in ("float", "half"):
        raise ExportError(f"precision {precision!r}: expected 'float' or 'half'")
    dataset = _open_dataset(Path(dataset_dir))
    if subjects:
        unknown = sorted(set(subjects) - set(dataset.subjects))
        if unknown:
            raise ExportError(
                f"{dataset.path}: no subject(s) {', '.join(unknown)} "
                f"(subjects: {', '.join(dataset.subjects)})"
            )
    keys = dataset.select(subjects=list(subjects) if subjects else None)
    # Every name is checked before the first file is written, so a bad one leaves no partial export.
    for what, names in (
        ("subject", dataset.subjects),
        ("camera", dataset.cameras),
        ("pattern", dataset.patterns),
    ):
        for name in names:
            check_name(name, what, str(dataset.path / INDEX_NAME))
    with output_lock(out):
        return _write_export(dataset, keys, Path(out), precision, progress)


def _write_export(
    dataset: NormalizedDataset, keys: list[str], out: Path, precision: str, progress: bool
) -> dict:
    """The files of an export of ``keys`` into ``out`` (which the caller has locked)."""
    (out / "dataset.json").unlink(missing_ok=True)  # incomplete until rewritten at the end
    cameras = []
    for key in progress_bar(keys, desc=f"export {dataset.name}", unit="image", disable=not progress):
        row, image, _ = dataset.decoded(key)
        image_file, mask_file, valid_file = image_paths(
            row.subject, row.frame, row.camera, row.pattern, where=f"{dataset.path} row {key!r}"
        )
        _write_file(out / image_file, encode_exr(image, precision))
        _write_file(out / mask_file, row.mask)  # already an 8-bit PNG: copied as stored
        _write_file(out / valid_file, encode_mask(row.valid_pixels()))
        cameras.append(camera_entry(row, image_file, mask_file, valid_file))
    lights = dataset.lights()
    info = dataset.manifest.info
    description = {
        "dataset": info.name,
        "kind": info.kind,
        "lighting": info.lighting,
        "template_mesh_id": info.template_mesh_id,
        "provenance": info.provenance.to_json(),
        "source": str(dataset.path.resolve()),
        "image_format": f"OpenEXR {precision} RGB, ZIP",
        "conventions": EXPORT_CONVENTIONS,
        "counts": {
            "images": len(cameras),
            "subjects": len({c["subject"] for c in cameras}),
            "lights": len(lights),
        },
    }
    atomic_write_bytes(out / "cameras.json", json.dumps(cameras, indent=1).encode())
    atomic_write_bytes(out / "lights.json", json.dumps(lights, indent=1).encode())
    atomic_write_bytes(out / "dataset.json", json.dumps(description, indent=1).encode())
    return {
        "dataset": info.name,
        "images": len(cameras),
        **{k: description["counts"][k] for k in ("subjects", "lights")},
    }
