"""`export-dataset`: EXR images, masks and JSON tables that round-trip to the normalized rows."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.format.codecs import decode_mask
from relightanyone.format.examples import write_example_dataset
from relightanyone.format.reader import NormalizedDataset
from relightanyone.pipelines.cli import export_dataset_command
from relightanyone.pipelines.export import ExportError, export_dataset, read_exr


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return write_example_dataset(tmp_path_factory.mktemp("datasets"), subjects=("s000", "s001"))


def test_export_round_trip_images_masks_and_cameras(example, tmp_path):
    out = tmp_path / "export"
    result = CliRunner().invoke(export_dataset_command, [str(example), "--format", "exr", "--out", str(out)])
    assert result.exit_code == 0, result.output
    dataset = NormalizedDataset(example)
    cameras = json.loads((out / "cameras.json").read_text())
    assert [c["key"] for c in cameras] == dataset.keys
    for entry in cameras:
        row, image, mask = dataset.decoded(entry["key"])
        assert entry["image"] == f"{row.subject}/{row.frame:06d}/{row.camera}/{row.pattern}.exr"
        exported = read_exr(out / entry["image"])
        assert exported.dtype == np.float32 and np.array_equal(exported, image)
        assert np.array_equal(decode_mask((out / entry["mask"]).read_bytes()), mask)
        assert entry["valid"] == f"{row.subject}/{row.frame:06d}/{row.camera}/{row.pattern}.valid.png"
        assert np.array_equal(decode_mask((out / entry["valid"]).read_bytes()) == 1.0, row.valid_pixels())
        np.testing.assert_array_equal(np.array(entry["K"]), row.K)
        np.testing.assert_array_equal(np.array(entry["w2c"]), row.w2c)
        assert (entry["width"], entry["height"]) == (row.width, row.height) == exported.shape[1::-1]
        assert (entry["subject"], entry["frame"], entry["camera"], entry["pattern"], entry["split"]) == (
            row.subject,
            row.frame,
            row.camera,
            row.pattern,
            row.split,
        )
    assert json.loads((out / "lights.json").read_text()) == json.loads(json.dumps(dataset.lights()))
    assert [light["index"] for light in json.loads((out / "lights.json").read_text())] == [0, 1]
    description = json.loads((out / "dataset.json").read_text())
    assert description["kind"] == "olat" and description["counts"] == {
        "images": 8,
        "subjects": 2,
        "lights": 2,
    }


def test_half_precision_and_subject_selection(example, tmp_path):
    summary = export_dataset(example, tmp_path, precision="half", subjects=("s001",), progress=False)
    assert summary == {"dataset": "demo", "images": 4, "subjects": 1, "lights": 2}
    assert not (tmp_path / "s000").exists()
    dataset = NormalizedDataset(example)
    key = dataset.select(subjects="s001")[0]
    _, image, _ = dataset.decoded(key)
    entry = json.loads((tmp_path / "cameras.json").read_text())[0]
    np.testing.assert_allclose(read_exr(tmp_path / entry["image"]), image, rtol=1e-3, atol=1e-4)
    with pytest.raises(ExportError, match="no subject"):
        export_dataset(example, tmp_path, subjects=("nobody",), progress=False)


def test_folder_that_is_not_one_dataset_is_refused(tmp_path):
    root = tmp_path / "root"
    for name in ("one", "two"):
        write_example_dataset(root, name=name, subjects=("s000",))
    with pytest.raises(ExportError, match=r"holds several datasets \(one, two\)"):
        export_dataset(root, tmp_path / "x", progress=False)
    result = CliRunner().invoke(cli, ["export-dataset", str(tmp_path), "--out", str(tmp_path / "y")])
    assert result.exit_code == 1 and "not a normalized dataset folder" in result.output
