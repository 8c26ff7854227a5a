"""Splits: a published protocol reaches every row, training reads only training subjects, and an
evaluation of held-out subjects refuses any subject a run trained on."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner
from helpers.custom_capture import make_capture

from relightanyone.cli import cli
from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest.records import published_splits


def test_published_splits_reach_the_rows(tmp_path):
    capture = make_capture(tmp_path / "capture", subjects=("s1", "s2", "s3"), frames=(0,))
    protocol = tmp_path / "splits.json"
    protocol.write_text(json.dumps({"s2": "val", "s3": "test"}))  # s1 unlisted: train
    result = CliRunner().invoke(
        cli,
        ["ingest", "custom", str(capture), "--splits", str(protocol), "--out", str(tmp_path / "out")]
        + ["--preset", "tiny", "--workers", "1"],
    )
    assert result.exit_code == 0, result.output
    dataset = NormalizedDataset(tmp_path / "out" / "custom")
    for subject, split in {"s1": "train", "s2": "val", "s3": "test"}.items():
        keys = dataset.select(subjects=subject)
        assert keys and set(dataset.select(subjects=subject, splits=split)) == set(keys), subject


def test_a_protocol_with_an_unknown_split_is_refused(tmp_path):
    protocol = tmp_path / "splits.json"
    protocol.write_text(json.dumps({"s1": "train", "s2": "holdout"}))
    with pytest.raises(InputError, match="split values must be one of train, val, test"):
        published_splits(protocol)
