"""The one schema of the normalized dataset, format version 2.

Everything that is written to or read from ``<root>/<dataset>/`` is described here: the tables of the
image shards, ``meshes.arrow``, ``lights.arrow`` and the shard index, the file names of a dataset, the
manifest model, the quarantine entry, and typed rows with builders that check them. Writers and readers
import these definitions; no other module spells a field name of its own.

Each column is declared once, as a :class:`Column` (name, Arrow type, nullability, a one-line meaning,
and how a Python value is stored): the row dataclasses declare theirs as fields (:func:`column`), so the
Arrow schemas (:meth:`Table.schema`), the rows' conversions and the tables of ``docs/format.md``
(:meth:`Table.markdown`) all derive from the same declaration.
"""

from __future__ import annotations

import hashlib
import json
import math
import unicodedata
from collections.abc import Callable
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from functools import partial
from typing import Any

import numpy as np
import pyarrow as pa
import xxhash

from relightanyone.errors import InputError
from relightanyone.format.codecs import decode_valid, encode_valid, valid_bytes

FORMAT_VERSION = 2
DATASET_KINDS = ("olat", "flat", "synthetic-olat")
IMAGE_ENCODINGS = ("png16", "exr-half", "raw-f16")
SCHEMA_METADATA = {
    b"schema_version": str(FORMAT_VERSION).encode(),
    b"colour_space": b"scene-linear rgb",
    b"camera_convention": b"opencv, w2c row-major, metres",
}
# A stored pixel is valid when less than this fraction of its resampling weight falls on the zero padding
# past the source image's edge (float32 round-off of weights that sum to 1 stays far below it).
PADDING_WEIGHT_TOLERANCE = 1e-5
MANIFEST_NAME = "manifest.json"
MESHES_NAME = "meshes.arrow"
LIGHTS_NAME = "lights.arrow"
INDEX_NAME = "index.arrow"
QUARANTINE_NAME = "quarantine.jsonl"
SHARD_PATTERN = "images-{:05d}.arrow"
# Side files beside the shards: ingest's template mesh of meshes.arrow, its neck mask and its report, and
# the learned colour matrix the colour warm-up writes into a view of the dataset.
TEMPLATE_NAME = "template.obj"
NECK_MASK_NAME = "template_neck_mask.txt"
INGEST_REPORT_NAME = "ingest_report.json"
COLOUR_ALIGNMENT_NAME = "colour_alignment.json"
# The files a dataset may hold besides the manifest and the files it lists.
UNLISTED_FILE_NAMES = (
    QUARANTINE_NAME,
    TEMPLATE_NAME,
    NECK_MASK_NAME,
    INGEST_REPORT_NAME,
    COLOUR_ALIGNMENT_NAME,
)


def _unchanged(value: Any) -> Any:
    return value


@dataclass(frozen=True)
class Column:
    """One column of a table: its name, Arrow type, nullability and meaning, and how a row's Python
    value is stored in it (``to_arrow``) and read back (``from_arrow``)."""

    name: str
    arrow_type: pa.DataType
    meaning: str
    nullable: bool = False
    to_arrow: Callable[[Any], Any] = _unchanged
    from_arrow: Callable[[Any], Any] = _unchanged

    def arrow_field(self) -> pa.Field:
        return pa.field(self.name, self.arrow_type, nullable=self.nullable)


_COLUMN_KEY = "relightanyone.format.column"


def column(
    arrow_type: pa.DataType,
    meaning: str,
    *,
    nullable: bool = False,
    to_arrow: Callable[[Any], Any] = _unchanged,
    from_arrow: Callable[[Any], Any] = _unchanged,
    default: Any = MISSING,
) -> Any:
    """A dataclass field that is also a table column; the column takes the field's name."""
    declared = Column("", arrow_type, meaning, nullable, to_arrow, from_arrow)
    return field(default=default, metadata={_COLUMN_KEY: declared})


def _flat_floats(size: int, matrix: Any) -> list[float]:
    return np.asarray(matrix, dtype=np.float64).reshape(size).tolist()


def _float_matrix(shape: tuple[int, int], values: Any) -> np.ndarray:
    return np.asarray(values, dtype=np.float64).reshape(shape)


def matrix_column(shape: tuple[int, int], meaning: str) -> Any:
    """A float64 matrix field of ``shape``, stored row-major as a fixed-size list and read back with its
    2-D shape."""
    size = shape[0] * shape[1]
    return column(
        pa.list_(pa.float64(), size),
        meaning,
        to_arrow=partial(_flat_floats, size),
        from_arrow=partial(_float_matrix, shape),
    )


def _int_list(values: Any) -> list[int]:
    return [int(v) for v in values]


def _int_tuple(values: Any) -> tuple[int, ...]:
    return tuple(int(v) for v in values)


def row_columns(row_type: type) -> tuple[Column, ...]:
    """The columns a row dataclass declares with :func:`column`, in field order."""
    return tuple(
        replace(f.metadata[_COLUMN_KEY], name=f.name) for f in fields(row_type) if _COLUMN_KEY in f.metadata
    )


def _type_name(arrow_type: pa.DataType) -> str:
    """Arrow type as the documentation writes it: ``fixed_size_list<float64>[9]``, ``list<float32>``."""
    if pa.types.is_fixed_size_list(arrow_type):
        return f"fixed_size_list<{_type_name(arrow_type.value_type)}>[{arrow_type.list_size}]"
    if pa.types.is_list(arrow_type):
        return f"list<{_type_name(arrow_type.value_type)}>"
    return {pa.float64(): "float64", pa.float32(): "float32"}.get(arrow_type, str(arrow_type))


@dataclass(frozen=True)
class Table:
    """An Arrow table of the format: its ``table`` metadata value and its columns, in order."""

    name: str
    columns: tuple[Column, ...]

    def schema(self) -> pa.Schema:
        """The Arrow schema, with the format's metadata and this table's name."""
        fields_ = [c.arrow_field() for c in self.columns]
        return pa.schema(fields_).with_metadata({**SCHEMA_METADATA, b"table": self.name.encode()})

    def columns_named(self, *names: str) -> tuple[Column, ...]:
        """The columns called ``names``, in that order."""
        by_name = {c.name: c for c in self.columns}
        return tuple(by_name[name] for name in names)

    def markdown(self) -> str:
        """The documentation table: one line per column (name, Arrow type, meaning)."""
        lines = ["| field | Arrow type | meaning |", "|---|---|---|"]
        for c in self.columns:
            arrow_type = _type_name(c.arrow_type) + (", nullable" if c.nullable else "")
            lines.append(f"| `{c.name}` | {arrow_type} | {c.meaning} |")
        return "\n".join(lines) + "\n"


class SchemaError(InputError):
    """A row or manifest does not follow the format; the message names the item and the field."""


class UnsafeNameError(SchemaError):
    """A name that becomes a file or folder name (subject, camera, dataset, pattern, ...) is not safe as one;
    the message names it, where it came from and what to do."""


# The longest name that becomes one path component, in UTF-8 bytes: far below every file system's limit
# (255), so a name plus a suffix (".avatar", ".mask.png", "-avatars") always fits.
MAX_NAME_BYTES = 128


def name_problem(name: Any) -> str | None:
    """Why ``name`` cannot be one file or folder name, or None when it can.

    The rule for every name that becomes a path component (subject, camera, frame, dataset, pattern, light
    set, stage, export names): text, not empty, not ``.`` or ``..``, no leading dot, no ``/`` or ``\\``,
    no control character (NUL included), valid UTF-8 of at most ``MAX_NAME_BYTES`` bytes. Such a name can
    neither climb out of the folder it is written into nor hide in it.
    """
    if not isinstance(name, str):
        return f"is a {type(name).__name__}, not text"
    if not name:
        return "is empty"
    if name in (".", ".."):
        return "names a folder itself (. or ..)"
    if name.startswith("."):
        return "starts with a dot (a hidden file)"
    if "/" in name or "\\" in name:
        return "contains a path separator (/ or \\)"
    if any(unicodedata.category(c) == "Cc" for c in name):
        return "contains a control character"
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:
        return "is not valid UTF-8"
    if size > MAX_NAME_BYTES:
        return f"is {size} bytes long, more than {MAX_NAME_BYTES}"
    return None


def check_name(name: Any, what: str, where: str) -> str:
    """``name`` when it is safe as a file or folder name (:func:`name_problem`), else ``UnsafeNameError``
    naming ``what`` it is (subject, camera, ...) and ``where`` it came from (a file or folder)."""
    problem = name_problem(name)
    if problem is not None:
        raise UnsafeNameError(
            f"{where}: {what} name {name!r} {problem}; it becomes a file or folder name, so rename it "
            f"(letters, digits, '-', '_', no leading '.', at most {MAX_NAME_BYTES} bytes)"
        )
    return name


def make_image_key(
    dataset: str, subject: str, frame: int, camera: str, pattern: str, where: str = "image key"
) -> str:
    """The unique key of an image row; sorts by dataset, subject, frame, camera, pattern. Every part is a
    safe file name (:func:`check_name`); ``where`` says where the row comes from, for the error."""
    for name, value in (("dataset", dataset), ("subject", subject), ("camera", camera), ("pattern", pattern)):
        check_name(value, name, where)
    return f"{dataset}/{subject}/{int(frame):06d}/{camera}/{pattern}"


def make_mesh_key(subject: str, frame: int) -> str:
    """The unique key of a ``meshes.arrow`` row."""
    return f"{check_name(subject, 'subject', 'mesh key')}/{int(frame):06d}"


@dataclass
class ImageRow:
    """One image row: one stored image and its camera. Each field is a column of ``images-*.arrow``, in
    this order; matrices are numpy arrays: ``K`` (3, 3), ``w2c`` (4, 4), ``colour_matrix`` (3, 4).

    ``valid`` holds one bit per stored pixel (:func:`relightanyone.format.codecs.encode_valid`): set where
    the pixel's value comes from the source image alone, clear where its resampling footprint reaches the
    zero padding past the source's edge. Masks never cover a clear bit; losses and metrics ignore those
    pixels. The shards also hold a ``checksum`` column of every other column (:func:`row_checksum`), added by
    :meth:`to_arrow_dict` and verified by :meth:`from_arrow_dict`."""

    key: str = column(
        pa.string(), "unique: `<dataset>/<subject>/<frame:06d>/<camera>/<pattern>`; rows are sorted by it"
    )
    dataset: str = column(pa.string(), "dataset name; a safe file name")
    subject: str = column(pa.string(), "subject id; a safe file name")
    frame: int = column(pa.int32(), "frame number", to_arrow=int)
    camera: str = column(pa.string(), "camera name; a safe file name")
    pattern: str = column(
        pa.string(), "lighting: `full`, `olat-017`, or an environment-map name; a safe file name"
    )
    split: str = column(pa.string(), "`train`, `val`, `test`, ...")
    width: int = column(pa.int32(), "stored image width in pixels", to_arrow=int)
    height: int = column(pa.int32(), "stored image height in pixels", to_arrow=int)
    K: np.ndarray = matrix_column((3, 3), "3×3 intrinsics, row-major, in pixels of the stored image")
    w2c: np.ndarray = matrix_column((4, 4), "4×4 world-to-camera, row-major, OpenCV camera, last row 0 0 0 1")
    image: bytes = column(pa.binary(), "encoded linear RGB, see `image_encoding`")
    image_encoding: str = column(pa.string(), "`raw-f16` (default), `exr-half` or `png16`")
    mask: bytes = column(pa.binary(), "8-bit single-channel PNG, 255 = head; 0 wherever `valid` is clear")
    valid: bytes = column(
        pa.binary(),
        "valid pixels: one bit per stored pixel, row-major, most significant bit first (`np.packbits`); "
        "set where the pixel comes from the source image alone, clear where it reaches the zero padding "
        "past the source's edge",
    )
    crop: tuple[int, int, int, int] = column(
        pa.list_(pa.int32(), 4),
        "x0, y0, x1, y1 of the stored image in source pixels",
        to_arrow=_int_list,
        from_arrow=_int_tuple,
    )
    colour_matrix: np.ndarray = matrix_column(
        (3, 4),
        "3×4 colour correction already applied, row-major: `rgb = M[:, :3] @ rgb_source + M[:, 3]` "
        "(the black level folded into the offset column; zeros there for a 3×3 calibration)",
    )
    source: str = column(pa.string(), "path of the item inside the native dataset")
    source_sha256: str = column(pa.string(), "hex sha256 of that native file")

    def to_arrow_dict(self) -> dict[str, Any]:
        """The row as plain Python values in ``IMAGE_SCHEMA`` field order (matrices flattened row-major),
        with its ``checksum``."""
        validate_image_row(self)
        values = {c.name: c.to_arrow(getattr(self, c.name)) for c in ROW_COLUMNS}
        return {**values, CHECKSUM_COLUMN.name: row_checksum(values)}

    @classmethod
    def from_arrow_dict(cls, values: dict[str, Any]) -> ImageRow:
        """Inverse of ``to_arrow_dict``: matrices come back as float64 arrays of their 2-D shape. Raises
        ``SchemaError`` naming the row when its values do not match its checksum (corrupted bytes)."""
        if row_checksum(values) != values[CHECKSUM_COLUMN.name]:
            raise SchemaError(
                f"image row {row_label(values)}: its values do not match the row's checksum (the shard is "
                "corrupted); restore the dataset or re-ingest it"
            )
        return cls(**{c.name: c.from_arrow(values[c.name]) for c in ROW_COLUMNS})

    def valid_pixels(self) -> np.ndarray:
        """(H, W) bool: the pixels that come from the source image alone (the ``valid`` bits)."""
        return decode_valid(self.valid, self.height, self.width)


def row_label(values: dict[str, Any]) -> str:
    """How messages name an image row (from its Arrow values): key, dataset, subject, camera and frame."""
    return (
        f"{values['key']!r} (dataset {values['dataset']}, subject {values['subject']}, "
        f"camera {values['camera']}, frame {values['frame']})"
    )


def _checksum_bytes(value: Any) -> bytes:
    """The bytes a column's Arrow value adds to the checksum: binary as it is, text as UTF-8, integers as
    8 little-endian bytes, number lists as float64 (exact for the int32 crop too)."""
    if isinstance(value, bytes):
        return value
    if isinstance(value, str):
        return value.encode("utf-8")
    if isinstance(value, int):
        return value.to_bytes(8, "little", signed=True)
    return np.asarray(value, dtype="<f8").tobytes()


def row_checksum(values: dict[str, Any]) -> int:
    """The ``checksum`` column of a row given as its Arrow values (``to_arrow_dict``, or a shard row read
    back): xxh3-64 over every other column in schema order, each value's bytes preceded by their length,
    so bytes cannot move between columns unnoticed. The image, mask and valid bytes are nearly all of it:
    about 0.15 ms for a 1024² ``raw-f16`` row (``bench/loader.py``)."""
    digest = xxhash.xxh3_64()
    for c in ROW_COLUMNS:
        data = _checksum_bytes(values[c.name])
        digest.update(len(data).to_bytes(8, "little"))
        digest.update(data)
    return digest.intdigest()


ROW_COLUMNS = row_columns(ImageRow)
CHECKSUM_COLUMN = Column(
    "checksum",
    pa.uint64(),
    "xxh3-64 of every other column (`schema.row_checksum`: pixels, cameras, names), written by the shard "
    "writer and verified on every read",
    to_arrow=int,
)
IMAGE_TABLE = Table("images", (*ROW_COLUMNS, CHECKSUM_COLUMN))
IMAGE_SCHEMA = IMAGE_TABLE.schema()
# The metadata columns of every image row, copied into the index so the reader gets them in one go.
INDEX_COLUMNS = ("key", "subject", "frame", "camera", "pattern", "split")
INDEX_TABLE = Table(
    "index",
    (
        *IMAGE_TABLE.columns_named(*INDEX_COLUMNS),
        Column("shard", pa.int32(), "number of the shard holding the row (its place in the manifest's list)"),
        Column("batch_offset", pa.int64(), "byte offset of the row's record batch in that shard"),
    ),
)
INDEX_SCHEMA = INDEX_TABLE.schema()


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
    valid: np.ndarray | None = None,
) -> ImageRow:
    """Build and check an image row; the key is derived, ``crop`` defaults to the whole image,
    ``colour_matrix`` (3, 3) or (3, 4) to the identity (a 3×3 gets a zero offset column) and ``valid``
    ((H, W) bool) to every pixel."""
    if valid is not None and np.shape(valid) != (int(height), int(width)):
        raise SchemaError(f"valid must be a ({height}, {width}) bool map, got shape {np.shape(valid)}")
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
        valid=encode_valid(np.ones((int(height), int(width)), bool) if valid is None else valid),
        crop=tuple(int(v) for v in (crop if crop is not None else (0, 0, width, height))),
        colour_matrix=affine_colour_matrix(np.eye(3) if colour_matrix is None else colour_matrix),
        source=source,
        source_sha256=source_sha256,
    )
    validate_image_row(row)
    return row


def affine_colour_matrix(matrix: Any) -> np.ndarray:
    """(3, 4) float64 of a (3, 3) matrix (zero offset column) or a (3, 4) one (as it is)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape == (3, 3):
        return np.hstack([matrix, np.zeros((3, 1))])
    if matrix.shape != (3, 4):
        raise SchemaError(f"a colour matrix must be (3, 3) or (3, 4), got {matrix.shape}")
    return matrix


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
    expected = make_image_key(
        row.dataset, row.subject, row.frame, row.camera, row.pattern, where=f"{where} (from {row.source})"
    )
    if row.key != expected:
        raise SchemaError(f"{where}: key must be {expected!r}")
    if row.image_encoding not in IMAGE_ENCODINGS:
        raise SchemaError(f"{where}: image_encoding {row.image_encoding!r} is not one of {IMAGE_ENCODINGS}")
    if row.width <= 0 or row.height <= 0:
        raise SchemaError(f"{where}: width and height must be positive, got {row.width}x{row.height}")
    for name, shape in (("K", (3, 3)), ("w2c", (4, 4)), ("colour_matrix", (3, 4))):
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
    if len(row.valid) != valid_bytes(row.height, row.width):
        raise SchemaError(
            f"{where}: valid must hold {valid_bytes(row.height, row.width)} bytes (one bit per pixel), "
            f"got {len(row.valid)}"
        )
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


MESH_TABLE = Table(
    "meshes",
    (
        Column("key", pa.string(), "unique: `<subject>/<frame:06d>`"),
        *IMAGE_TABLE.columns_named("subject", "frame"),
        Column("vertex_count", pa.int32(), "V, the number of vertices"),
        Column(
            "vertices",
            pa.list_(pa.float32()),
            "V×3 flattened, canonical space, metres; V varies only between topologies",
        ),
    ),
)
MESH_SCHEMA = MESH_TABLE.schema()


@dataclass
class LightRow:
    """One rig light: position (3,) in metres in canonical space, linear RGB intensity (3,) in its OLAT
    pattern, and (when it differs) its intensity (3,) in the full-on pattern. Each field is a column of
    ``lights.arrow``, in this order."""

    index: int = column(pa.int32(), "light number in the rig")
    name: str = column(pa.string(), "the rig's name of the light")
    position_m: tuple[float, float, float] = column(
        pa.list_(pa.float64(), 3), "position in canonical space, metres"
    )
    intensity_rgb: tuple[float, float, float] = column(
        pa.list_(pa.float64(), 3), "linear RGB intensity in its OLAT pattern"
    )
    pattern: str = column(pa.string(), "the image pattern this light is on in, e.g. `olat-017`")
    full_on_intensity_rgb: tuple[float, float, float] | None = column(
        pa.list_(pa.float64(), 3),
        "intensity in the full-on pattern (light stages often shorten each light's exposure there); "
        "null when it equals `intensity_rgb` or is unknown",
        nullable=True,
        default=None,
    )

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


LIGHT_TABLE = Table("lights", row_columns(LightRow))
LIGHT_SCHEMA = LIGHT_TABLE.schema()
# Every table of the format, in the order docs/format.md describes them.
TABLES = (IMAGE_TABLE, INDEX_TABLE, MESH_TABLE, LIGHT_TABLE)


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
    accepted_checks: tuple[str, ...] = ()  # ingest convention checks overridden on purpose (--accept-check)

    def __post_init__(self) -> None:
        if self.kind not in DATASET_KINDS:
            raise SchemaError(f"dataset {self.name!r}: kind {self.kind!r} is not one of {DATASET_KINDS}")
        check_name(self.name, "dataset", f"dataset {self.name!r}")


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
            **({"accepted_checks": list(self.info.accepted_checks)} if self.info.accepted_checks else {}),
        }

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=2, sort_keys=False, ensure_ascii=False) + "\n"

    def listed_files(self) -> list[FileEntry]:
        """The files the manifest lists: shards, index, and the mesh and light tables when present."""
        return [*self.shards, self.index, *(e for e in (self.meshes, self.lights) if e is not None)]

    @classmethod
    def from_json(cls, values: dict[str, Any], where: str = "manifest.json") -> Manifest:
        """Parse a manifest; raises ``SchemaError`` naming ``where`` and the missing or bad field."""
        try:
            version = int(values["format_version"])
            if version != FORMAT_VERSION:
                raise SchemaError(format_version_problem(version, where))
            info = DatasetInfo(
                name=check_name(values["dataset"], "dataset", where),
                kind=values["kind"],
                template_mesh_id=values["template_mesh_id"],
                lighting=values["lighting"],
                provenance=Provenance.from_json(values["provenance"]),
                config_fingerprint=values["config_fingerprint"],
                accepted_checks=tuple(values.get("accepted_checks", ())),
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


def format_version_problem(version: int, where: str) -> str:
    """The one-line refusal of a dataset of another format version."""
    if version < FORMAT_VERSION:
        return (
            f"{where}: format version {version} was written by an earlier release; this one reads version "
            f"{FORMAT_VERSION} (rows carry a valid-pixel map, a 3×4 colour matrix and a checksum): re-ingest "
            "the capture with `relightanyone ingest` (or re-run the pipeline stage that wrote it)"
        )
    return f"{where}: format version {version} is newer than this release reads ({FORMAT_VERSION}); upgrade"


def fingerprint_config(config: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of a config (sorted keys), for ``DatasetInfo.config_fingerprint``."""
    canonical = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()
