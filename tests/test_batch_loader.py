"""The trainers' batch loader: a DataLoader of per-iteration batches whose worker processes give the
very batches, and so the very weights, of the synchronous path."""

from __future__ import annotations

import functools

import pytest
import torch
from helpers.stage1_world import tiny_stage1_preset, write_dataset

from relightanyone.format.torch_dataset import iteration_loader
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.data import Stage1Data
from relightanyone.model.train.stage1 import Stage1Config, stage1_batch, train_stage1

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return [write_dataset(tmp_path_factory.mktemp("loader-world"), "da", seed=0)]


def test_workers_yield_the_synchronous_batches_in_order(world):
    data = Stage1Data(world, held_out_per_subject=1)
    make_batch = functools.partial(stage1_batch, data, 2, 2, 0, 32, 7)
    synchronous = [make_batch(iteration) for iteration in range(3, 8)]
    for workers in (0, 2):
        loaded = list(iteration_loader(make_batch, 3, 8, workers=workers))
        assert len(loaded) == len(synchronous)
        for ours, theirs in zip(loaded, synchronous, strict=True):
            assert ours.keys() == theirs.keys()
            assert all(torch.equal(ours[k], theirs[k]) for k in ours)


def test_training_with_loader_workers_gives_the_same_weights(world, tmp_path):
    preset = tiny_stage1_preset(iterations=4, checkpoint_every=4, held_out_cameras=0)
    runs = {}
    for workers in (0, 2):
        out = tmp_path / f"workers{workers}"
        train_stage1(Stage1Config(world, out, preset, progress=False, evaluate=False, loader_workers=workers))
        runs[workers] = load_checkpoint(out / "checkpoint.pt")["model"]
    assert all(torch.equal(runs[0][name], runs[2][name]) for name in runs[0])
