"""The one schema of the normalized dataset, format version 1.

Everything that is written to or read from ``<root>/<dataset>/`` is described here: the Arrow schemas of
the image shards, ``meshes.arrow``, ``lights.arrow`` and the shard index, the manifest model, the quarantine
entry, and typed rows with builders that check them. Writers and readers import these definitions; no
other module spells a field name of its own.

Image row fields (one row per stored image)::

    key             string   unique; "<dataset>/<subject>/<frame:06d>/<camera>/<pattern>"
    dataset         string
    subject         string
    frame           int32
    camera          string
    pattern         string   "full", "olat-017", or an environment-map name
    split           string   "train", "val", "test", ...
    width, height   int32    size of the stored image in pixels
    K               fixed_size_list<float64>[9]    3x3 intrinsics, row-major, pixels of the stored image
    w2c             fixed_size_list<float64>[16]   4x4 world-to-camera, row-major, OpenCV camera
    image           binary   encoded linear RGB (see ``image_encoding`` and ``codecs``)
    image_encoding  string   "png16" | "exr-half" | "raw-f16"
    mask            binary   8-bit single-channel PNG, 255 = foreground
    crop            fixed_size_list<int32>[4]      x0, y0, x1, y1 of the stored image in source pixels
    colour_matrix   fixed_size_list<float64>[9]    3x3 row-major matrix already applied: rgb_out = M @ rgb_src
    source          string   path of the item inside the native dataset
    source_sha256   string   hex sha256 of the native file
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
import pyarrow as pa

FORMAT_VERSION = 1
DATASET_KINDS = ("olat", "flat", "synthetic-olat")
IMAGE_ENCODINGS = ("png16", "exr-half", "raw-f16")
SCHEMA_METADATA = {
    b"schema_version": str(FORMAT_VERSION).encode(),
    b"colour_space": b"scene-linear rgb",
    b"camera_convention": b"opencv, w2c row-major, metres",
}
MANIFEST_NAME = "manifest.json"
MESHES_NAME = "meshes.arrow"
LIGHTS_NAME = "lights.arrow"
INDEX_NAME = "index.arrow"
QUARANTINE_NAME = "quarantine.jsonl"
# Side files ingest writes beside the shards: the template mesh of meshes.arrow and its neck mask.
TEMPLATE_NAME = "template.obj"
NECK_MASK_NAME = "template_neck_mask.txt"
SHARD_PATTERN = "images-{:05d}.arrow"


def _with_metadata(schema: pa.Schema, table: str) -> pa.Schema:
    return schema.with_metadata({**SCHEMA_METADATA, b"table": table.encode()})


IMAGE_SCHEMA = _with_metadata(
    pa.schema(
        [
            pa.field("key", pa.string(), nullable=False),
            pa.field("dataset", pa.string(), nullable=False),
            pa.field("subject", pa.string(), nullable=False),
            pa.field("frame", pa.int32(), nullable=False),
            pa.field("camera", pa.string(), nullable=False),
            pa.field("pattern", pa.string(), nullable=False),
            pa.field("split", pa.string(), nullable=False),
            pa.field("width", pa.int32(), nullable=False),
            pa.field("height", pa.int32(), nullable=False),
            pa.field("K", pa.list_(pa.float64(), 9), nullable=False),
            pa.field("w2c", pa.list_(pa.float64(), 16), nullable=False),
            pa.field("image", pa.binary(), nullable=False),
            pa.field("image_encoding", pa.string(), nullable=False),
            pa.field("mask", pa.binary(), nullable=False),
            pa.field("crop", pa.list_(pa.int32(), 4), nullable=False),
            pa.field("colour_matrix", pa.list_(pa.float64(), 9), nullable=False),
            pa.field("source", pa.string(), nullable=False),
            pa.field("source_sha256", pa.string(), nullable=False),
        ]
    ),
    "images",
)

MESH_SCHEMA = _with_metadata(
    pa.schema(
        [
            pa.field("key", pa.string(), nullable=False),
            pa.field("subject", pa.string(), nullable=False),
            pa.field("frame", pa.int32(), nullable=False),
            pa.field("vertex_count", pa.int32(), nullable=False),
            # Flattened (V*3,) float32 in canonical space, metres; V varies only between topologies.
            pa.field("vertices", pa.list_(pa.float32()), nullable=False),
        ]
    ),
    "meshes",
)

LIGHT_SCHEMA = _with_metadata(
    pa.schema(
        [
            pa.field("index", pa.int32(), nullable=False),
            pa.field("name", pa.string(), nullable=False),
            pa.field("position_m", pa.list_(pa.float64(), 3), nullable=False),
            pa.field("intensity_rgb", pa.list_(pa.float64(), 3), nullable=False),
            pa.field("pattern", pa.string(), nullable=False),
            # The light's intensity in the full-on pattern (light stages often shorten each light's
            # exposure there); null when it equals intensity_rgb or is unknown.
            pa.field("full_on_intensity_rgb", pa.list_(pa.float64(), 3), nullable=True),
        ]
    ),
    "lights",
)

# The metadata columns of every image row plus where the row lives; read in one go by the reader.
INDEX_SCHEMA = _with_metadata(
    pa.schema(
        [
            pa.field("key", pa.string(), nullable=False),
            pa.field("subject", pa.string(), nullable=False),
            pa.field("frame", pa.int32(), nullable=False),
            pa.field("camera", pa.string(), nullable=False),
            pa.field("pattern", pa.string(), nullable=False),
            pa.field("split", pa.string(), nullable=False),
            pa.field("shard", pa.int32(), nullable=False),
            pa.field("batch_offset", pa.int64(), nullable=False),
        ]
    ),
    "index",
)

INDEX_COLUMNS = ("key", "subject", "frame", "camera", "pattern", "split")


class SchemaError(ValueError):
    """A row or manifest does not follow the format; the message names the item and the field."""


def make_image_key(dataset: str, subject: str, frame: int, camera: str, pattern: str) -> str:
    """The unique key of an image row; sorts by dataset, subject, frame, camera, pattern."""
    for name, value in (("dataset", dataset), ("subject", subject), ("camera", camera), ("pattern", pattern)):
        if not value or "/" in value:
            raise SchemaError(f"{name} {value!r} must be non-empty and must not contain '/'")
    return f"{dataset}/{subject}/{int(frame):06d}/{camera}/{pattern}"


def make_mesh_key(subject: str, frame: int) -> str:
    """The unique key of a ``meshes.arrow`` row."""
    return f"{subject}/{int(frame):06d}"


@dataclass
class ImageRow:
    """One image row. Matrices are numpy arrays: ``K`` (3, 3), ``w2c`` (4, 4), ``colour_matrix`` (3, 3)."""

    key: str
    dataset: str
    subject: str
    frame: int
    camera: str
    pattern: str
    split: str
    width: int
    height: int
    K: np.ndarray
    w2c: np.ndarray
    image: bytes
    image_encoding: str
    mask: bytes
    crop: tuple[int, int, int, int]
    colour_matrix: np.ndarray
    source: str
    source_sha256: str

    def to_arrow_dict(self) -> dict[str, Any]:
        """The row as plain Python values in ``IMAGE_SCHEMA`` field order (matrices flattened row-major)."""
        validate_image_row(self)
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["K"] = np.asarray(self.K, dtype=np.float64).reshape(9).tolist()
        out["w2c"] = np.asarray(self.w2c, dtype=np.float64).reshape(16).tolist()
        out["colour_matrix"] = np.asarray(self.colour_matrix, dtype=np.float64).reshape(9).tolist()
        out["crop"] = [int(v) for v in self.crop]
        out["frame"], out["width"], out["height"] = int(self.frame), int(self.width), int(self.height)
        return out

    @classmethod
    def from_arrow_dict(cls, values: dict[str, Any]) -> ImageRow:
        """Inverse of ``to_arrow_dict``: matrices come back as float64 arrays of their 2-D shape."""
        kwargs = {f.name: values[f.name] for f in fields(cls)}
        kwargs["K"] = np.asarray(values["K"], dtype=np.float64).reshape(3, 3)
        kwargs["w2c"] = np.asarray(values["w2c"], dtype=np.float64).reshape(4, 4)
        kwargs["colour_matrix"] = np.asarray(values["colour_matrix"], dtype=np.float64).reshape(3, 3)
        kwargs["crop"] = tuple(int(v) for v in values["crop"])
        return cls(**kwargs)


def build_image_row(
    *,
    dataset: str,
    subject: str,
    frame: int,
    camera: str,
    pattern: str,
    split: str,
    K: np.ndarray,
    w2c: np.ndarray,
    image: bytes,
    image_encoding: str,
    mask: bytes,
    width: int,
    height: int,
    source: str,
    source_sha256: str,
    crop: tuple[int, int, int, int] | None = None,
    colour_matrix: np.ndarray | None = None,
) -> ImageRow:
    """Build and check an image row; the key is derived, ``crop`` defaults to the whole image and
    ``colour_matrix`` to the identity."""
    row = ImageRow(
        key=make_image_key(dataset, subject, frame, camera, pattern),
        dataset=dataset,
        subject=subject,
        frame=int(frame),
        camera=camera,
        pattern=pattern,
        split=split,
        width=int(width),
        height=int(height),
        K=np.asarray(K, dtype=np.float64).reshape(3, 3),
        w2c=np.asarray(w2c, dtype=np.float64).reshape(4, 4),
        image=bytes(image),
        image_encoding=image_encoding,
        mask=bytes(mask),
        crop=tuple(int(v) for v in (crop if crop is not None else (0, 0, width, height))),
        colour_matrix=np.eye(3)
        if colour_matrix is None
        else np.asarray(colour_matrix, np.float64).reshape(3, 3),
        source=source,
        source_sha256=source_sha256,
    )
    validate_image_row(row)
    return row


def camera_problems(K: np.ndarray, w2c: np.ndarray, width: int, height: int) -> list[str]:
    """Problems of a camera: ``K`` (3, 3) finite with positive focals and the principal point within one
    image size of the image; ``w2c`` (4, 4) finite with an orthonormal, right-handed rotation and last row
    0 0 0 1. Returns human-readable problems, empty when the camera is sane."""
    problems = []
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    w2c = np.asarray(w2c, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(K)):
        problems.append("K has non-finite entries")
    else:
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            problems.append(f"K focal lengths must be positive, got fx={K[0, 0]:g} fy={K[1, 1]:g}")
        # Crops can push the principal point off-centre, but never further than one image size away.
        if not (-width <= K[0, 2] <= 2 * width and -height <= K[1, 2] <= 2 * height):
            problems.append(
                f"K principal point ({K[0, 2]:g}, {K[1, 2]:g}) is far outside the {width}x{height} image"
            )
        if np.abs(K[2] - (0.0, 0.0, 1.0)).max() > 1e-5 or K[1, 0] != 0:
            problems.append(
                f"K last row must be 0 0 1 and K[1,0] must be 0, got {K[2].tolist()}, {K[1, 0]:g}"
            )
    if not np.all(np.isfinite(w2c)):
        problems.append("w2c has non-finite entries")
    else:
        rotation = w2c[:3, :3]
        if np.abs(rotation @ rotation.T - np.eye(3)).max() > 1e-5 or np.linalg.det(rotation) < 0:
            problems.append("w2c rotation is not orthonormal and right-handed")
        if np.abs(w2c[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-5:
            problems.append(f"w2c last row must be 0 0 0 1, got {w2c[3].tolist()}")
    return problems


def validate_image_row(row: ImageRow) -> None:
    """Raise ``SchemaError`` naming the key and the field when ``row`` breaks the format."""
    where = f"image row {row.key!r}"
    expected = make_image_key(row.dataset, row.subject, row.frame, row.camera, row.pattern)
    if row.key != expected:
        raise SchemaError(f"{where}: key must be {expected!r}")
    if row.image_encoding not in IMAGE_ENCODINGS:
        raise SchemaError(f"{where}: image_encoding {row.image_encoding!r} is not one of {IMAGE_ENCODINGS}")
    if row.width <= 0 or row.height <= 0:
        raise SchemaError(f"{where}: width and height must be positive, got {row.width}x{row.height}")
    for name, shape in (("K", (3, 3)), ("w2c", (4, 4)), ("colour_matrix", (3, 3))):
        if np.asarray(getattr(row, name)).shape != shape:
            raise SchemaError(f"{where}: {name} must have shape {shape}")
    problems = camera_problems(row.K, row.w2c, row.width, row.height)
    if problems:
        raise SchemaError(f"{where}: " + "; ".join(problems))
    if not np.all(np.isfinite(row.colour_matrix)):
        raise SchemaError(f"{where}: colour_matrix has non-finite entries")
    x0, y0, x1, y1 = row.crop
    if not (x1 > x0 and y1 > y0):
        raise SchemaError(f"{where}: crop {row.crop} must have x1 > x0 and y1 > y0")
    if not row.image or not row.mask:
        raise SchemaError(f"{where}: image and mask must not be empty")
    if len(row.source_sha256) != 64:
        raise SchemaError(f"{where}: source_sha256 must be 64 hex characters")


@dataclass
class MeshRow:
    """Tracked vertices of one (subject, frame): ``vertices`` (V, 3) float32, canonical space, metres."""

    subject: str
    frame: int
    vertices: np.ndarray

    @property
    def key(self) -> str:
        return make_mesh_key(self.subject, self.frame)

    def to_arrow_dict(self) -> dict[str, Any]:
        vertices = np.asarray(self.vertices, dtype=np.float32)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
            raise SchemaError(f"mesh row {self.key!r}: vertices must be a finite (V, 3) array")
        return {
            "key": self.key,
            "subject": self.subject,
            "frame": int(self.frame),
            "vertex_count": int(vertices.shape[0]),
            "vertices": vertices.reshape(-1),
        }


@dataclass
class LightRow:
    """One rig light: position (3,) in metres in canonical space, linear RGB intensity (3,) in its OLAT
    pattern, and (when it differs) its intensity (3,) in the full-on pattern."""

    index: int
    name: str
    position_m: tuple[float, float, float]
    intensity_rgb: tuple[float, float, float]
    pattern: str
    full_on_intensity_rgb: tuple[float, float, float] | None = None

    def to_arrow_dict(self) -> dict[str, Any]:
        values = asdict(self)
        for name in ("position_m", "intensity_rgb", "full_on_intensity_rgb"):
            if values[name] is None and name == "full_on_intensity_rgb":
                continue
            vector = [float(v) for v in values[name]]
            if len(vector) != 3 or not all(math.isfinite(v) for v in vector):
                raise SchemaError(f"light {self.index} ({self.name}): {name} must be 3 finite numbers")
            values[name] = vector
        return values


@dataclass
class QuarantineEntry:
    """An input item that was refused: which item, where it came from, why, and at which stage."""

    item: str
    source: str
    reason: str
    stage: str

    def to_json_line(self) -> str:
        return json.dumps(asdict(self), sort_keys=True, ensure_ascii=False)


@dataclass
class Provenance:
    """Where a dataset comes from; ``parents`` carries the provenance of datasets it was derived from."""

    source_dataset: str
    licence: str
    tracker: str = ""
    template: str = ""
    parents: list[Provenance] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "source_dataset": self.source_dataset,
            "licence": self.licence,
            "tracker": self.tracker,
            "template": self.template,
            "parents": [p.to_json() for p in self.parents],
        }

    @classmethod
    def from_json(cls, values: dict[str, Any]) -> Provenance:
        return cls(
            source_dataset=values["source_dataset"],
            licence=values["licence"],
            tracker=values.get("tracker", ""),
            template=values.get("template", ""),
            parents=[cls.from_json(p) for p in values.get("parents", [])],
        )

    def derived(self, source_dataset: str, licence: str, **kwargs: str) -> Provenance:
        """Provenance of a dataset made from this one: this entry (and its ancestors) become a parent."""
        return Provenance(source_dataset, licence, parents=[self], **kwargs)


@dataclass
class DatasetInfo:
    """What the producer of a dataset knows before writing rows."""

    name: str
    kind: str
    template_mesh_id: str
    lighting: str
    provenance: Provenance
    config_fingerprint: str

    def __post_init__(self) -> None:
        if self.kind not in DATASET_KINDS:
            raise SchemaError(f"dataset {self.name!r}: kind {self.kind!r} is not one of {DATASET_KINDS}")
        if not self.name or "/" in self.name:
            raise SchemaError(f"dataset name {self.name!r} must be non-empty and must not contain '/'")


@dataclass
class FileEntry:
    """A finished file of the dataset: name, rows, sha256 and size in bytes."""

    file: str
    rows: int
    sha256: str
    bytes: int


@dataclass
class Manifest:
    """``manifest.json``: written last; a dataset without one is incomplete."""

    info: DatasetInfo
    counts: dict[str, int]
    shards: list[FileEntry]
    index: FileEntry
    meshes: FileEntry | None
    lights: FileEntry | None
    quarantined: int
    format_version: int = FORMAT_VERSION
    quarantine: FileEntry | None = None  # quarantine.jsonl (rows = entries); None in a manifest without it

    def to_json(self) -> dict[str, Any]:
        return {
            "format_version": self.format_version,
            "dataset": self.info.name,
            "kind": self.info.kind,
            "template_mesh_id": self.info.template_mesh_id,
            "lighting": self.info.lighting,
            "config_fingerprint": self.info.config_fingerprint,
            "provenance": self.info.provenance.to_json(),
            "counts": dict(sorted(self.counts.items())),
            "shards": [asdict(s) for s in self.shards],
            "index": asdict(self.index),
            "meshes": asdict(self.meshes) if self.meshes else None,
            "lights": asdict(self.lights) if self.lights else None,
            "quarantined": self.quarantined,
            "quarantine": asdict(self.quarantine) if self.quarantine else None,
        }

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=2, sort_keys=False, ensure_ascii=False) + "\n"

    @classmethod
    def from_json(cls, values: dict[str, Any], where: str = "manifest.json") -> Manifest:
        """Parse a manifest; raises ``SchemaError`` naming ``where`` and the missing or bad field."""
        try:
            version = int(values["format_version"])
            if version != FORMAT_VERSION:
                raise SchemaError(
                    f"{where}: format_version {version} is not supported (expected {FORMAT_VERSION})"
                )
            info = DatasetInfo(
                name=values["dataset"],
                kind=values["kind"],
                template_mesh_id=values["template_mesh_id"],
                lighting=values["lighting"],
                provenance=Provenance.from_json(values["provenance"]),
                config_fingerprint=values["config_fingerprint"],
            )
            optional = {
                k: FileEntry(**values[k]) if values.get(k) else None
                for k in ("meshes", "lights", "quarantine")
            }
            return cls(
                info=info,
                counts={k: int(v) for k, v in values["counts"].items()},
                shards=[FileEntry(**s) for s in values["shards"]],
                index=FileEntry(**values["index"]),
                quarantined=int(values["quarantined"]),
                format_version=version,
                **optional,
            )
        except KeyError as error:
            raise SchemaError(f"{where}: missing field {error.args[0]!r}") from None
        except TypeError as error:
            raise SchemaError(f"{where}: malformed entry ({error})") from None


def fingerprint_config(config: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of a config (sorted keys), for ``DatasetInfo.config_fingerprint``."""
    canonical = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()
