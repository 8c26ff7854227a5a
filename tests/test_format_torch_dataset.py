"""The PyTorch view of a normalized dataset."""

from __future__ import annotations

import pickle

import numpy as np
import torch

from relightanyone.format.codecs import decode_image
from relightanyone.format.examples import example_rows
from relightanyone.format.schema import DatasetInfo, Provenance
from relightanyone.format.shards import ShardWriter
from relightanyone.format.torch_dataset import NormalizedTorchDataset


def _write(root):
    writer = ShardWriter(
        root / "flat",
        DatasetInfo("flat", "flat", "flame", "even", Provenance("Ava-256", "CC"), "c"),
        max_shard_bytes=15_000,
    )
    writer.begin()
    for subject in ("s000", "s001"):
        with writer.part(subject) as part:
            for row in example_rows(
                "flat", (subject,), cameras=3, split="train" if subject == "s000" else "test"
            ):
                part.add(row)
    writer.commit()
    return root / "flat"


def test_dataloader_with_two_workers_returns_every_row(tmp_path):
    dataset = NormalizedTorchDataset(_write(tmp_path))
    assert len(dataset) == 6 and pickle.loads(pickle.dumps(dataset)).keys == dataset.keys
    loader = torch.utils.data.DataLoader(dataset, batch_size=2, num_workers=2)
    keys = []
    for batch in loader:
        assert batch["image"].shape == (2, 3, 32, 24) and batch["image"].dtype == torch.float32
        assert batch["mask"].shape == (2, 1, 32, 24) and batch["K"].shape == (2, 3, 3)
        assert batch["w2c"].shape == (2, 4, 4) and torch.allclose(batch["w2c"][:, 3, 3], torch.ones(2))
        keys += batch["key"]
    assert keys == dataset.keys


def test_filters_and_colour_matrix_on_load(tmp_path):
    path = _write(tmp_path)
    test_split = NormalizedTorchDataset(path, splits="test")
    assert [item["subject"] for item in test_split] == ["s001"] * 3
    swap = np.array([[0, 0, 1], [0, 1, 0], [2, 0, 0]], np.float32)
    plain, coloured = (
        NormalizedTorchDataset(path, cameras="cam01"),
        NormalizedTorchDataset(path, cameras="cam01", colour_matrix=swap),
    )
    a, b = plain[0]["image"], coloured[0]["image"]
    assert torch.allclose(b[0], a[2]) and torch.allclose(b[2], 2 * a[0]) and torch.allclose(b[1], a[1])
    row = plain.source.row(plain.keys[0])
    expected = torch.from_numpy(decode_image(row.image, row.image_encoding)).permute(2, 0, 1)
    assert torch.equal(a, expected)
