"""What every row of format version 2 carries: its valid pixels, the colour matrix as applied, and a
checksum of its pixels that every read verifies."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pyarrow as pa
import pytest
import torch

from relightanyone.errors import InputError
from relightanyone.format.arrow_io import read_message_at
from relightanyone.format.codecs import encode_image, encode_mask
from relightanyone.format.examples import write_example_dataset
from relightanyone.format.reader import CorruptRowError, NormalizedDataset
from relightanyone.format.schema import (
    DatasetInfo,
    ImageRow,
    Provenance,
    SchemaError,
    build_image_row,
)
from relightanyone.format.shards import ShardWriter
from relightanyone.format.torch_dataset import NormalizedTorchDataset, collate_rows, random_crop
from relightanyone.format.validate import validate_path
from relightanyone.model.metrics import masked_psnr
from relightanyone.model.train.losses import composite_over_background, masked_l1
from relightanyone.render.camera import look_at_w2c

SIZE = 16  # the rows' side in pixels
PADDING_COLUMNS = 5  # columns 0..4 of the padded row lie past the source image's left edge


def _row(camera: str, image: np.ndarray, mask: np.ndarray, valid: np.ndarray | None):
    K = np.array([[20.0, 0, (SIZE - 1) / 2], [0, 20.0, (SIZE - 1) / 2], [0, 0, 1]])
    return build_image_row(
        dataset="padded",
        subject="s000",
        frame=3,
        camera=camera,
        pattern="full",
        split="train",
        K=K,
        w2c=look_at_w2c([0.0, 0.0, 1.0], np.zeros(3), [0.0, 1.0, 0.0]),
        image=encode_image(image),
        image_encoding="raw-f16",
        mask=encode_mask(mask),
        width=SIZE,
        height=SIZE,
        source=f"{camera}.png",
        source_sha256=hashlib.sha256(camera.encode()).hexdigest(),
        crop=(-PADDING_COLUMNS, 0, SIZE - PADDING_COLUMNS, SIZE),
        valid=valid,
    )


def _padded_dataset(root, mask_on_padding: bool):
    """One row whose left columns are padding, its image black there; the mask covers the whole head
    disc, padding included when ``mask_on_padding`` (what ingest wrote before it knew the valid region)."""
    valid = np.ones((SIZE, SIZE), bool)
    valid[:, :PADDING_COLUMNS] = False
    yy, xx = np.mgrid[:SIZE, :SIZE]
    head = (xx - 6.0) ** 2 + (yy - 8.0) ** 2 < 30.0
    image = np.repeat((0.5 * (head & valid)).astype(np.float32)[..., None], 3, axis=2)
    mask = head if mask_on_padding else head & valid
    info = DatasetInfo("padded", "flat", "t", "flat", Provenance("test", "test"), "cfg")
    writer = ShardWriter(root / "padded", info)
    writer.begin()
    with writer.part("s000") as part:
        part.add(_row("cam00", image, mask, valid))
    writer.commit()
    return root / "padded", head, valid


def test_a_mask_on_padding_fails_validate_naming_the_row(tmp_path):
    clean, _, _ = _padded_dataset(tmp_path / "clean", mask_on_padding=False)
    assert validate_path(clean) == []
    bad, head, valid = _padded_dataset(tmp_path / "bad", mask_on_padding=True)
    (problem,) = [str(p) for p in validate_path(bad)]
    outside = int((head & ~valid).sum())
    assert "images-00000.arrow row 0: 'padded/s000/000003/cam00/full'" in problem
    assert "subject s000, camera cam00, frame 3" in problem
    assert f"mask covers {outside} pixel(s) outside the source image" in problem


def test_padding_pixels_count_in_no_loss_or_metric(tmp_path):
    dataset, head, valid = _padded_dataset(tmp_path, mask_on_padding=True)
    item = NormalizedTorchDataset(dataset)[0]
    # The stored mask wrongly covers padding; the reader's mask does not, and says which pixels are valid.
    assert torch.equal(item["valid"][0], torch.from_numpy(valid.astype(np.float32)))
    assert torch.equal(item["mask"][0], torch.from_numpy((head & valid).astype(np.float32)))
    cropped = random_crop(item, 12, np.random.default_rng(0))
    batch = collate_rows([cropped])
    assert torch.equal(batch["valid"] * batch["mask"], batch["mask"])

    # Two renders that differ only on padding: the same loss over the whole crop and the same metric.
    truth = batch["image"]
    render = truth.clone()
    other = torch.where(batch["valid"].bool(), truth, torch.full_like(truth, 0.9))
    alpha = batch["mask"]
    background = torch.tensor([[0.2, 0.3, 0.4]])
    losses = []
    for candidate in (render, other):
        compared, target = composite_over_background(candidate, alpha, truth, batch["mask"], background)
        losses.append(float(masked_l1(compared, target, batch["valid"])[0]))
    assert losses[0] == losses[1] == 0.0
    target, mask = item["image"][None], item["mask"][None]
    near = target * 0.9
    near_but_padding = torch.where(item["valid"].bool(), near, torch.ones_like(near))
    assert float(masked_psnr(near_but_padding, target, mask)[0]) == float(masked_psnr(near, target, mask)[0])


def test_colour_matrix_is_stored_3x4(tmp_path):
    image = np.full((SIZE, SIZE, 3), 0.25, np.float32)
    mask = np.ones((SIZE, SIZE), bool)
    row = _row("cam00", image, mask, None)
    assert row.colour_matrix.shape == (3, 4) and np.array_equal(
        row.colour_matrix, np.hstack([np.eye(3), np.zeros((3, 1))])
    )
    assert row.valid_pixels().all()
    affine = np.hstack([np.diag([1.1, 1.0, 0.9]), [[0.01], [0.02], [-0.03]]])
    row = build_image_row(**{**_row_kwargs(row), "colour_matrix": affine})
    assert np.array_equal(row.colour_matrix, affine)
    with pytest.raises(SchemaError, match=r"\(3, 3\) or \(3, 4\)"):
        build_image_row(**{**_row_kwargs(row), "colour_matrix": np.eye(4)})


def _row_kwargs(row) -> dict:
    names = ("dataset", "subject", "frame", "camera", "pattern", "split", "K", "w2c", "image")
    names += ("image_encoding", "mask", "width", "height", "source", "source_sha256", "crop")
    return {name: getattr(row, name) for name in names}


def _pixel_regions(dataset_dir):
    """(start, end) byte ranges of the record-batch bodies (the compressed buffers: image, mask, valid
    bits and the other values) of every row of the first shard."""
    dataset = NormalizedDataset(dataset_dir)
    source = pa.memory_map(str(dataset_dir / "images-00000.arrow"))
    regions = []
    for offset in dataset.index.column("batch_offset").to_pylist():
        message = read_message_at(source, offset)
        end = offset + len(message.serialize())
        regions.append((end - message.body.size, end))
    return regions


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return write_example_dataset(tmp_path_factory.mktemp("rows"), subjects=("s000",))


def _flipped_copy(pristine, tmp_path, position: int):
    copy = shutil.copytree(pristine, tmp_path / f"flip{position}")
    shard = copy / "images-00000.arrow"
    data = bytearray(shard.read_bytes())
    data[position] ^= 0x10
    shard.write_bytes(bytes(data))
    return copy


def test_a_flipped_byte_never_returns_different_pixels(pristine, tmp_path):
    truth = NormalizedDataset(pristine)
    expected = {key: truth.decoded(key) for key in truth.keys}
    regions = _pixel_regions(pristine)
    inside = np.concatenate([np.arange(start, end) for start, end in regions])
    positions = inside[np.linspace(0, inside.size - 1, 20).astype(int)]
    caught = 0
    for position in positions:
        copy = _flipped_copy(pristine, tmp_path, int(position))
        dataset = NormalizedDataset(copy)
        failed = []
        for key in dataset.keys:
            try:
                row, image, mask = dataset.decoded(key)
            except InputError as error:
                assert "images-00000.arrow" in str(error) and key in str(error), error
                failed.append(key)
                continue
            _, true_image, true_mask = expected[key]
            assert np.array_equal(image, true_image) and np.array_equal(mask, true_mask), (position, key)
            true_row = expected[key][0]
            assert np.array_equal(row.valid_pixels(), true_row.valid_pixels())
            # The checksum covers every column: cameras and names come back unchanged too.
            assert np.array_equal(row.K, true_row.K) and np.array_equal(row.w2c, true_row.w2c), key
            assert (row.crop, row.source, row.split) == (true_row.crop, true_row.source, true_row.split)
        # validate names exactly the rows the reader refused, with their dataset, subject, camera and frame.
        row_problems = [p.message for p in validate_path(copy) if p.row is not None]
        named = {
            key for key in dataset.keys for m in row_problems if f"'{key}' (dataset demo, subject s000" in m
        }
        assert named == set(failed), (position, named, failed)
        caught += len(failed)
    assert caught >= 15  # most flips land in pixel bytes and are caught, the rest in bytes no pixel reads


def test_a_corrupted_row_is_named_by_the_reader_and_by_validate(pristine, tmp_path):
    start, end = _pixel_regions(pristine)[1]
    copy = _flipped_copy(pristine, tmp_path, (start + end) // 2)
    dataset = NormalizedDataset(copy)
    key = dataset.keys[1]
    with pytest.raises(CorruptRowError, match=rf"images-00000.arrow: .*{key}"):
        dataset.row(key)
    assert dataset.decoded(dataset.keys[0])[0].key == dataset.keys[0]  # the other rows read
    messages = [str(p) for p in validate_path(copy)]
    assert any("images-00000.arrow: sha256 differs" in m for m in messages)
    row = NormalizedDataset(pristine).row(key)
    assert any(
        "images-00000.arrow row 1" in m
        and f"subject {row.subject}, camera {row.camera}, frame {row.frame}" in m
        and ("checksum" in m or "cannot be read" in m)
        for m in messages
    ), messages


def test_a_dataset_of_format_version_1_asks_for_a_re_ingest(pristine, tmp_path):
    copy = shutil.copytree(pristine, tmp_path / "old")
    manifest = json.loads((copy / "manifest.json").read_text())
    (copy / "manifest.json").write_text(json.dumps({**manifest, "format_version": 1}))
    with pytest.raises(InputError, match="format version 1 was written by an earlier release.*re-ingest"):
        NormalizedDataset(copy)


def test_the_checksum_covers_the_cameras_and_names_too():
    row = _row("cam00", np.full((SIZE, SIZE, 3), 0.25, np.float32), np.ones((SIZE, SIZE), bool), None)
    values = row.to_arrow_dict()
    assert ImageRow.from_arrow_dict(values).key == row.key
    for name, changed in (
        ("K", [*values["K"][:2], values["K"][2] + 1e-9, *values["K"][3:]]),
        ("split", "val"),
    ):
        with pytest.raises(SchemaError, match="do not match the row's checksum"):
            ImageRow.from_arrow_dict({**values, name: changed})
