"""`validate` finds each kind of damage and names the file; `inspect` summarizes and draws."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pytest
from click.testing import CliRunner

from relightanyone.format.arrow_io import StreamFileWriter
from relightanyone.format.cli import inspect_command, validate_command
from relightanyone.format.examples import write_example_dataset as write_demo
from relightanyone.format.preview import render_contact_sheet
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import IMAGE_SCHEMA, row_checksum
from relightanyone.format.validate import validate_path
from relightanyone.hashing import sha256_file


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return write_demo(tmp_path_factory.mktemp("pristine"), max_shard_bytes=20_000)


@pytest.fixture
def damaged(pristine, tmp_path):
    return shutil.copytree(pristine, tmp_path / "demo")


def _messages(path):
    return [str(p) for p in validate_path(path)]


def test_pristine_dataset_is_clean_and_cli_exits_zero(pristine):
    assert validate_path(pristine.parent) == []
    result = CliRunner().invoke(validate_command, [str(pristine)])
    assert result.exit_code == 0 and "OK" in result.output


def test_truncated_shard(damaged):
    shard = damaged / "images-00001.arrow"
    shard.write_bytes(shard.read_bytes()[:-100])
    assert any("images-00001.arrow: truncated" in m for m in _messages(damaged))


def test_flipped_byte(damaged):
    shard = damaged / "images-00000.arrow"
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0x01
    shard.write_bytes(bytes(data))
    assert any("images-00000.arrow: sha256 differs" in m for m in _messages(damaged))


def test_missing_shard_and_cli_exit_code(damaged):
    (damaged / "images-00002.arrow").unlink()
    assert any("images-00002.arrow: listed in manifest.json but missing" in m for m in _messages(damaged))
    result = CliRunner().invoke(validate_command, [str(damaged)])
    assert result.exit_code == 1 and "images-00002.arrow" in result.output


def test_shard_listed_twice(damaged):
    manifest = json.loads((damaged / "manifest.json").read_text())
    manifest["shards"].append(manifest["shards"][0])
    (damaged / "manifest.json").write_text(json.dumps(manifest))
    messages = _messages(damaged)
    assert any("manifest.json: shard images-00000.arrow is listed 2 times" in m for m in messages)


def test_unlisted_shard_and_unsupported_version(damaged):
    shutil.copy(damaged / "images-00000.arrow", damaged / "images-00009.arrow")
    assert any("images-00009.arrow: shard is not listed" in m for m in _messages(damaged))
    (damaged / "images-00009.arrow").unlink()
    (damaged / "manifest.json").write_text(json.dumps({"format_version": 3}))
    assert any("format version 3 is newer than this release reads" in m for m in _messages(damaged))
    (damaged / "manifest.json").write_text(json.dumps({"format_version": 1}))
    (message,) = _messages(damaged)
    assert "format version 1 was written by an earlier release" in message and "re-ingest" in message


def _rewrite_shard(dataset_dir, name, mutate):
    """Rewrite shard ``name`` with ``mutate(rows)`` applied and re-list it in the manifest, as a writer with
    a bug would have done (the shard's hash and the rows' checksums are then right, their content wrong)."""
    rows = pa.ipc.open_stream(pa.memory_map(str(dataset_dir / name))).read_all().to_pylist()
    mutate(rows)
    for row in rows:
        row["checksum"] = row_checksum(row)
    writer = StreamFileWriter(dataset_dir / name, IMAGE_SCHEMA)
    for row in rows:
        writer.write(pa.RecordBatch.from_pylist([row], schema=IMAGE_SCHEMA))
    writer.finish()
    manifest = json.loads((dataset_dir / "manifest.json").read_text())
    for entry in manifest["shards"]:
        if entry["file"] == name:
            entry.update(sha256=sha256_file(dataset_dir / name), bytes=(dataset_dir / name).stat().st_size)
    (dataset_dir / "manifest.json").write_text(json.dumps(manifest))


def test_bad_cameras_undecodable_images_and_duplicate_keys_name_file_and_row(damaged):
    def break_rows(rows):
        rows[1]["K"] = [-100.0, 0, 12, 0, 100, 16, 0, 0, 1]
        rows[1]["w2c"] = [2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
        rows[2]["image"] = b"not an image"
        rows[3]["height"] = 30

    _rewrite_shard(damaged, "images-00000.arrow", break_rows)
    messages = _messages(damaged)
    assert any("images-00000.arrow row 1:" in m and "focal lengths must be positive" in m for m in messages)
    assert any("images-00000.arrow row 1:" in m and "not orthonormal" in m for m in messages)
    assert any("images-00000.arrow row 2:" in m and "image does not decode" in m for m in messages)
    assert any("images-00000.arrow row 3:" in m and "declared (30, 24)" in m for m in messages)

    first_key = NormalizedDataset(damaged).keys[0]
    _rewrite_shard(damaged, "images-00001.arrow", lambda rows: rows[0].update(key=first_key))
    assert any(
        "images-00001.arrow row 0: key" in m and "also in images-00000.arrow row 0" in m
        for m in _messages(damaged)
    )


def test_quarantine_is_hashed_and_its_entries_counted(pristine, damaged):
    manifest = json.loads((pristine / "manifest.json").read_text())
    entry = manifest["quarantine"]
    assert entry["file"] == "quarantine.jsonl" and entry["rows"] == manifest["quarantined"] == 3
    assert entry["sha256"] == sha256_file(pristine / "quarantine.jsonl")
    path = damaged / "quarantine.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:-1]))  # an entry dropped
    messages = _messages(damaged)
    assert any("quarantine.jsonl: truncated" in m for m in messages), messages
    assert any("quarantine.jsonl: 2 entries, manifest.json says 3" in m for m in messages), messages
    text = "".join(lines)
    at = text.index('"reason": "') + len('"reason": "')
    path.write_text(text[:at] + ("X" if text[at] != "X" else "Y") + text[at + 1 :])  # same size, other bytes
    assert any("quarantine.jsonl: sha256 differs" in m for m in _messages(damaged))
    path.unlink()
    messages = _messages(damaged)
    assert any("quarantine.jsonl: listed in manifest.json but missing" in m for m in messages), messages


def test_an_older_manifest_without_the_quarantine_entry_is_still_counted(damaged):
    manifest_path = damaged / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    del manifest["quarantine"]
    manifest_path.write_text(json.dumps(manifest))
    assert validate_path(damaged) == []
    (damaged / "quarantine.jsonl").write_text("")
    assert any("quarantine.jsonl: 0 entries, manifest.json says 3" in m for m in _messages(damaged))


def test_inspect_prints_summary_and_writes_contact_sheet(pristine, tmp_path):
    out = tmp_path / "sheet.png"
    result = CliRunner().invoke(inspect_command, [str(pristine.parent), "--out", str(out), "--samples", "4"])
    assert result.exit_code == 0, result.output
    assert "dataset demo  kind=olat" in result.output and "subjects (3)" in result.output
    assert "quarantined 3" in result.output and out.stat().st_size > 0


def test_contact_sheet_draws_mask_outlines():
    image = np.full((40, 40, 3), 0.2, np.float32)
    mask = np.zeros((40, 40))
    mask[10:30, 10:30] = 1
    sheet = render_contact_sheet([image, image], [mask, None], ["with", "without"], tile=40)
    assert sheet.shape == (58, 80, 3) and sheet.dtype == np.uint8
    outline = np.all(sheet == (255, 64, 32), axis=-1)
    assert outline[:40, :40].sum() > 40 and outline[:, 40:].sum() == 0
