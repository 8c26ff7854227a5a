"""The PyTorch view of a normalized dataset: filters, keys, colour matrices, pickling, DataLoader batches."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
import torch

from relightanyone.format.codecs import decode_image, decode_mask
from relightanyone.format.colour_alignment import write_learned_colour_matrix
from relightanyone.format.examples import example_rows
from relightanyone.format.schema import DatasetInfo, Provenance, make_image_key
from relightanyone.format.shards import ShardWriter
from relightanyone.format.torch_dataset import NormalizedTorchDataset, collate_rows, image_hwc


def _write(root):
    """s000 (train) and s001 (test), 3 cameras, patterns full and olat-000; s000 also has frame 1."""
    writer = ShardWriter(
        root / "flat",
        DatasetInfo("flat", "flat", "flame", "even", Provenance("Ava-256", "CC"), "c"),
        max_shard_bytes=15_000,
    )
    writer.begin()
    for subject in ("s000", "s001"):
        rows = example_rows(
            "flat",
            (subject,),
            cameras=3,
            patterns=("full", "olat-000"),
            split="train" if subject == "s000" else "test",
        )
        if subject == "s000":
            rows += [
                dataclasses.replace(
                    row, frame=1, key=make_image_key("flat", subject, 1, row.camera, row.pattern)
                )
                for row in rows
            ]
        with writer.part(subject) as part:
            for row in rows:
                part.add(row)
    writer.commit()
    return root / "flat"


def test_dataloader_with_two_workers_collates_every_row(tmp_path):
    dataset = NormalizedTorchDataset(_write(tmp_path), patterns="full")
    assert len(dataset) == 9 and pickle.loads(pickle.dumps(dataset)).keys == dataset.keys
    loader = torch.utils.data.DataLoader(dataset, batch_size=2, num_workers=2, collate_fn=collate_rows)
    keys, indices = [], []
    for batch in loader:
        size = len(batch["key"])
        assert batch["image"].shape == (size, 3, 32, 24) and batch["image"].dtype == torch.float32
        assert batch["mask"].shape == (size, 1, 32, 24) and batch["K"].shape == (size, 3, 3)
        assert batch["K"].dtype == batch["w2c"].dtype == torch.float64  # as stored
        assert torch.equal(batch["w2c"][:, 3, 3], torch.ones(size, dtype=torch.float64))
        assert batch["width"] == [24] * size and batch["pattern"] == ["full"] * size
        keys += batch["key"]
        indices += batch["index"]
    assert keys == dataset.keys and indices == list(range(9))


def test_an_item_is_its_row_decoded(tmp_path):
    dataset = NormalizedTorchDataset(_write(tmp_path))
    item, row = dataset[4], dataset.row(4)
    assert item["key"] == row.key == dataset.keys[4] and item["index"] == 4
    assert (item["subject"], item["frame"], item["camera"], item["pattern"], item["split"]) == (
        row.subject,
        row.frame,
        row.camera,
        row.pattern,
        row.split,
    )
    assert np.array_equal(image_hwc(item), decode_image(row.image, row.image_encoding))
    assert image_hwc(item).flags.c_contiguous
    assert np.array_equal(item["mask"][0].numpy(), decode_mask(row.mask))
    assert np.array_equal(item["K"].numpy(), row.K) and np.array_equal(item["w2c"].numpy(), row.w2c)


def test_filters_select_rows_in_key_order_and_keys_keep_their_order(tmp_path):
    path = _write(tmp_path)
    test_split = NormalizedTorchDataset(path, splits="test")
    assert test_split.column("subject") == ["s001"] * 6
    assert [item["subject"] for item in test_split] == ["s001"] * 6
    chosen = NormalizedTorchDataset(
        path, subjects="s000", frames=1, cameras=["cam02", "cam00"], patterns="olat-000"
    )
    assert chosen.keys == ["flat/s000/000001/cam00/olat-000", "flat/s000/000001/cam02/olat-000"]
    assert chosen.column("frame") == [1, 1] and chosen.column("camera") == ["cam00", "cam02"]
    assert NormalizedTorchDataset(path, subjects="s000").column("frame") == [0] * 6 + [1] * 6
    assert len(NormalizedTorchDataset(path, subjects="s001", frames=1)) == 0
    keys = ["flat/s001/000000/cam02/full", "flat/s000/000001/cam00/full", "flat/s001/000000/cam00/olat-000"]
    exact = NormalizedTorchDataset(path, keys=keys)
    assert exact.keys == keys and [item["key"] for item in exact] == keys
    assert NormalizedTorchDataset(path, keys=keys, patterns="full").keys == keys[:2]  # filters still apply
    with pytest.raises(ValueError, match=r"flat: no image rows \['flat/s009/000000/cam00/full'\]"):
        NormalizedTorchDataset(path, keys=["flat/s009/000000/cam00/full"])
    with pytest.raises(ValueError, match="no index column 'width'"):
        exact.column("width")


def plain_image(rows: NormalizedTorchDataset, position: int) -> torch.Tensor:
    row = rows.row(position)
    return torch.from_numpy(decode_image(row.image, row.image_encoding)).permute(2, 0, 1)


def test_colour_matrix_given_or_learned_is_applied_on_load(tmp_path):
    path = _write(tmp_path)
    swap = np.array([[0, 0, 1], [0, 1, 0], [2, 0, 0]], np.float32)
    plain, coloured = (
        NormalizedTorchDataset(path, cameras="cam01"),
        NormalizedTorchDataset(path, cameras="cam01", colour_matrix=swap),
    )
    a, b = plain[0]["image"], coloured[0]["image"]
    assert torch.allclose(b[0], a[2]) and torch.allclose(b[2], 2 * a[0]) and torch.allclose(b[1], a[1])
    row = plain.row(0)
    expected = torch.from_numpy(decode_image(row.image, row.image_encoding)).permute(2, 0, 1)
    assert torch.equal(a, expected)
    # "learned": the folder's colour_alignment.json when there is one, nothing otherwise.
    assert NormalizedTorchDataset(path, colour_matrix="learned").colour_matrix_of("cam01") is None
    write_learned_colour_matrix(path, swap)
    learned = NormalizedTorchDataset(path, cameras="cam01", colour_matrix="learned")
    assert np.array_equal(learned.colour_matrix_of("cam01"), swap) and torch.equal(learned[0]["image"], b)
    assert torch.equal(pickle.loads(pickle.dumps(learned))[0]["image"], b)
    # A camera with its own matrix uses it; the others keep the dataset's.
    write_learned_colour_matrix(path, np.eye(3), cameras={"cam01": swap})
    per_camera = NormalizedTorchDataset(path, colour_matrix="learned")
    for position in range(len(per_camera)):
        item = per_camera[position]
        plain_item = plain_image(per_camera, position)
        expected = torch.einsum("ij,jhw->ihw", torch.from_numpy(swap), plain_item)
        assert torch.allclose(item["image"], expected if item["camera"] == "cam01" else plain_item)
    assert len(set(per_camera.column("camera"))) > 1
    with pytest.raises(ValueError, match="must be a"):
        NormalizedTorchDataset(path, colour_matrix="linear")
    with pytest.raises(ValueError, match=r"must be \(3, 3\), got \(2, 2\)"):
        NormalizedTorchDataset(path, colour_matrix=np.eye(2))


def test_collate_names_the_field_whose_shapes_differ():
    items = [{"image": torch.zeros(3, 4, 4), "key": "a"}, {"image": torch.zeros(3, 5, 4), "key": "b"}]
    with pytest.raises(ValueError, match=r"differ in image shape: \[\(3, 4, 4\), \(3, 5, 4\)\]"):
        collate_rows(items)
    batch = collate_rows(items[:1] * 2)
    assert batch["image"].shape == (2, 3, 4, 4) and batch["key"] == ["a", "a"]
