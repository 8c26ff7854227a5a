"""Schema rows, manifest model and image codecs of the normalized format."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from relightanyone.format.codecs import (
    PNG16_LINEAR_MAX,
    CodecError,
    decode_image,
    decode_mask,
    encode_image,
    encode_mask,
)
from relightanyone.format.examples import example_rows, face_like_image
from relightanyone.format.schema import (
    IMAGE_SCHEMA,
    INDEX_SCHEMA,
    LIGHT_SCHEMA,
    MESH_SCHEMA,
    TABLES,
    DatasetInfo,
    FileEntry,
    ImageRow,
    Manifest,
    Provenance,
    SchemaError,
    UnsafeNameError,
    camera_problems,
    check_name,
    make_image_key,
    make_mesh_key,
    name_problem,
)

DOCS = Path(__file__).resolve().parents[1] / "docs" / "format.md"


def _v2(table: str, fields: list[pa.Field]) -> pa.Schema:
    return pa.schema(fields).with_metadata(
        {
            b"schema_version": b"2",
            b"colour_space": b"scene-linear rgb",
            b"camera_convention": b"opencv, w2c row-major, metres",
            b"table": table.encode(),
        }
    )


# Format version 2 as written on disk, spelled out field by field: the schemas derived from the column
# declarations must stay identical to it, so existing datasets read and shards stay byte-identical.
FORMAT_V2 = {
    "images": _v2(
        "images",
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
            pa.field("valid", pa.binary(), nullable=False),
            pa.field("crop", pa.list_(pa.int32(), 4), nullable=False),
            pa.field("colour_matrix", pa.list_(pa.float64(), 12), nullable=False),
            pa.field("source", pa.string(), nullable=False),
            pa.field("source_sha256", pa.string(), nullable=False),
            pa.field("checksum", pa.uint64(), nullable=False),
        ],
    ),
    "meshes": _v2(
        "meshes",
        [
            pa.field("key", pa.string(), nullable=False),
            pa.field("subject", pa.string(), nullable=False),
            pa.field("frame", pa.int32(), nullable=False),
            pa.field("vertex_count", pa.int32(), nullable=False),
            pa.field("vertices", pa.list_(pa.float32()), nullable=False),
        ],
    ),
    "lights": _v2(
        "lights",
        [
            pa.field("index", pa.int32(), nullable=False),
            pa.field("name", pa.string(), nullable=False),
            pa.field("position_m", pa.list_(pa.float64(), 3), nullable=False),
            pa.field("intensity_rgb", pa.list_(pa.float64(), 3), nullable=False),
            pa.field("pattern", pa.string(), nullable=False),
            pa.field("full_on_intensity_rgb", pa.list_(pa.float64(), 3), nullable=True),
        ],
    ),
    "index": _v2(
        "index",
        [
            pa.field("key", pa.string(), nullable=False),
            pa.field("subject", pa.string(), nullable=False),
            pa.field("frame", pa.int32(), nullable=False),
            pa.field("camera", pa.string(), nullable=False),
            pa.field("pattern", pa.string(), nullable=False),
            pa.field("split", pa.string(), nullable=False),
            pa.field("shard", pa.int32(), nullable=False),
            pa.field("batch_offset", pa.int64(), nullable=False),
        ],
    ),
}


@pytest.mark.parametrize(
    "table, schema",
    [("images", IMAGE_SCHEMA), ("meshes", MESH_SCHEMA), ("lights", LIGHT_SCHEMA), ("index", INDEX_SCHEMA)],
)
def test_derived_schemas_are_format_version_2_to_the_byte(table, schema):
    assert schema.equals(FORMAT_V2[table], check_metadata=True)
    assert schema.serialize().to_pybytes() == FORMAT_V2[table].serialize().to_pybytes()


@pytest.mark.parametrize("table", TABLES, ids=lambda t: t.name)
def test_docs_tables_are_generated_from_the_schema(table):
    # Regenerate with: python -c "from relightanyone.format.schema import TABLES; print(TABLES[i].markdown())"
    assert table.markdown() in DOCS.read_text(encoding="utf-8"), (
        f"docs/format.md: the {table.name} table is out of date; replace it with:\n{table.markdown()}"
    )


@pytest.mark.parametrize("encoding", ["png16", "exr-half", "raw-f16"])
def test_codec_round_trip_is_close_and_float32(encoding):
    image, _ = face_like_image(24, 20, seed=3)
    decoded = decode_image(encode_image(image, encoding), encoding)
    assert decoded.dtype == np.float32 and decoded.shape == (24, 20, 3)
    # half floats keep ~11 bits of mantissa; the PNG scale has a fixed step of 4/65535
    tolerance = PNG16_LINEAR_MAX / 65535 if encoding == "png16" else 1e-3 * image.max()
    assert np.abs(decoded - image).max() <= tolerance


def test_raw_f16_bytes_are_numpys_float16_rounding():
    # The fast conversion must round like numpy (to nearest even), across the whole half range:
    # subnormals, ties, the largest finite value and a value that rounds to it.
    rng = np.random.default_rng(7)
    values = rng.random(30_000).astype(np.float32) * np.float32(2.0) ** rng.integers(-26, 16, 30_000)
    values[:6] = [2.0**-24 * 0.5, 2.0**-24 * 1.5, 2.0**-14, 1.0 + 2.0**-11, 65504.0, 65490.0]
    image = values.reshape(100, 100, 3)
    data = encode_image(image, "raw-f16")
    assert data[16:] == image.astype("<f2").tobytes()
    assert np.array_equal(decode_image(data, "raw-f16"), image.astype("<f2").astype(np.float32))


def test_png16_clips_above_its_linear_range_and_encoding_is_deterministic():
    image = np.full((4, 4, 3), 10.0, np.float32)
    assert np.allclose(decode_image(encode_image(image, "png16"), "png16"), PNG16_LINEAR_MAX)
    assert encode_image(image * 0.1, "exr-half") == encode_image(image * 0.1, "exr-half")


def test_codecs_refuse_bad_input():
    with pytest.raises(CodecError, match="non-finite"):
        encode_image(np.full((2, 2, 3), np.nan, np.float32), "raw-f16")
    with pytest.raises(CodecError, match="shape"):
        encode_image(np.zeros((2, 2), np.float32), "png16")
    with pytest.raises(CodecError, match="malformed"):
        decode_image(encode_image(np.zeros((2, 2, 3)), "raw-f16")[:-2], "raw-f16")
    with pytest.raises(CodecError, match="unknown image encoding"):
        encode_image(np.zeros((2, 2, 3)), "jpeg")


def test_mask_round_trip():
    mask = np.zeros((5, 7), bool)
    mask[1:4, 2:6] = True
    decoded = decode_mask(encode_mask(mask))
    assert decoded.dtype == np.float32 and np.array_equal(decoded, mask.astype(np.float32))


def test_image_row_arrow_round_trip_and_key():
    row = example_rows(cameras=1)[0]
    values = row.to_arrow_dict()
    assert list(values) == IMAGE_SCHEMA.names
    assert values["K"] == row.K.reshape(9).tolist() and values["crop"] == [0, 0, 24, 32]
    back = ImageRow.from_arrow_dict(values)
    assert (
        back.key == make_image_key("example", "s000", 0, "cam00", "full") == "example/s000/000000/cam00/full"
    )
    assert np.array_equal(back.w2c, row.w2c) and back.crop == (0, 0, 24, 32)
    assert back.K.shape == (3, 3) and back.colour_matrix.dtype == np.float64


def test_bad_rows_name_the_key_and_the_field():
    row = example_rows(cameras=1)[0]
    row.K = row.K * np.array([[-1, 1, 1], [1, 1, 1], [1, 1, 1]])
    with pytest.raises(SchemaError, match=r"example/s000/000000/cam00/full.*focal"):
        row.to_arrow_dict()
    with pytest.raises(SchemaError, match="subject name 'a/b' contains a path separator"):
        make_image_key("d", "a/b", 0, "c", "full")


UNSAFE_NAMES = ("..", ".", "", "a/b", "a\\b", ".hidden", "nul\x00byte", "line\nbreak", "é" * 65)


@pytest.mark.parametrize("name", UNSAFE_NAMES)
def test_a_name_that_is_not_one_safe_file_name_is_refused(name):
    assert name_problem(name) is not None
    with pytest.raises(UnsafeNameError, match=r"^capture/x: camera name .* rename it"):
        check_name(name, "camera", "capture/x")
    with pytest.raises(UnsafeNameError):
        make_image_key("d", name, 0, "c", "full")
    with pytest.raises(UnsafeNameError):
        make_mesh_key(name, 0)


@pytest.mark.parametrize("name", ("s000", "cam-01", "EXP_neutral", "220700191", "env-studio.small", "é" * 64))
def test_ordinary_names_are_safe(name):
    assert name_problem(name) is None and check_name(name, "subject", "here") == name


def test_camera_checks():
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    assert camera_problems(K, np.eye(4), 100, 80) == []
    scaled = np.eye(4)
    scaled[:3, :3] *= 2
    assert any("orthonormal" in p for p in camera_problems(K, scaled, 100, 80))
    bad_last_row = np.eye(4)
    bad_last_row[3, 0] = 1
    assert any("last row" in p for p in camera_problems(K, bad_last_row, 100, 80))
    far = K.copy()
    far[0, 2] = 1e5
    assert any("principal point" in p for p in camera_problems(far, np.eye(4), 100, 80))


def test_manifest_json_round_trip_carries_parent_provenance():
    capture = Provenance("FaceOLAT", "research-only EULA", tracker="VHAP", template="FLAME 2023")
    expanded = capture.derived("FaceOLAT synthetic OLAT", "derived, same terms as parents", tracker="VHAP")
    entry = FileEntry("images-00000.arrow", 3, "a" * 64, 100)
    info = DatasetInfo("faceolat-expanded", "synthetic-olat", "flame", "OLAT 331 lights", expanded, "f" * 64)
    manifest = Manifest(
        info, {"images": 3}, [entry], FileEntry("index.arrow", 3, "b" * 64, 10), None, None, 0
    )
    parsed = Manifest.from_json(json.loads(manifest.dumps()))
    assert parsed.info.provenance.parents[0].source_dataset == "FaceOLAT"
    assert parsed.info.provenance.parents[0].licence == "research-only EULA"
    assert parsed.dumps() == manifest.dumps()
    broken = json.loads(manifest.dumps())
    del broken["kind"]
    with pytest.raises(SchemaError, match="missing field 'kind'"):
        Manifest.from_json(broken, where="x/manifest.json")
    with pytest.raises(SchemaError, match="kind 'hdr'"):
        DatasetInfo("d", "hdr", "flame", "", capture, "")
