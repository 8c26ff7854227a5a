"""The stage-1 batch loader against the synchronous path: writes ``bench/results/dataloader.json``.

Two measures on the given normalized datasets, tiny preset unless told otherwise:

* ``batches``: seconds per batch of making the batches alone, synchronously in the loop (what training did
  before the loader), through the loader without workers, and through the loader with ``--workers``
  processes (the first batch, which starts the workers, is not timed);
* ``training``: stage-1 seconds per iteration (``metrics.json``) with ``--loader-workers 0`` and with
  ``--workers``, and whether the two runs end with identical weights.

Usage::

    python bench/dataloader.py --data out/d1 --data out/d2 [--iterations 40] [--workers 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

from relightanyone.format.torch_dataset import iteration_loader
from relightanyone.model.networks.presets import get_preset
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.data import Stage1Data
from relightanyone.model.train.stage1 import Stage1Config, stage1_batch, train_stage1

RESULTS = Path(__file__).resolve().parent / "results" / "dataloader.json"


def seconds_per_batch(batches, count: int) -> float:
    """Mean seconds per batch over ``count`` batches after the first one."""
    iterator = iter(batches)
    next(iterator)
    began = time.perf_counter()
    for _ in range(count):
        next(iterator)
    return (time.perf_counter() - began) / count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", action="append", required=True, type=Path)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    preset = get_preset(args.preset)
    data = Stage1Data(args.data, preset.held_out_cameras)
    make_batch = functools.partial(
        stage1_batch, data, preset.batch_size, preset.batch_size, 0, preset.crop_size, 0
    )
    count = args.iterations
    batches = {
        "synchronous": seconds_per_batch((make_batch(i) for i in range(count + 1)), count),
        "loader_0_workers": seconds_per_batch(iteration_loader(make_batch, 0, count + 1), count),
        f"loader_{args.workers}_workers": seconds_per_batch(
            iteration_loader(make_batch, 0, count + 1, workers=args.workers), count
        ),
    }
    training = {}
    weights = {}
    with tempfile.TemporaryDirectory() as folder:
        for workers in (0, args.workers):
            out = Path(folder) / f"workers{workers}"
            run = preset.replace(iterations=args.iterations, checkpoint_every=args.iterations)
            metrics = train_stage1(
                Stage1Config(args.data, out, run, progress=False, evaluate=False, loader_workers=workers)
            )
            training[f"loader_{workers}_workers"] = metrics["seconds_per_iteration"]
            weights[workers] = load_checkpoint(out / "checkpoint.pt")["model"]
    identical = all(torch.equal(weights[0][k], weights[args.workers][k]) for k in weights[0])
    payload = {
        "benchmark": "stage-1 batch loader",
        "preset": args.preset,
        "datasets": [Path(d).name for d in args.data],  # names only: the folders are this machine's
        "iterations": args.iterations,
        "seconds_per_batch": {k: round(v, 5) for k, v in batches.items()},
        "training_seconds_per_iteration": {k: round(v, 4) for k, v in training.items()},
        "identical_weights": identical,
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "load_average_1_5_15_min": list(os.getloadavg()),
        },
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(payload, indent=2) + "\n")
    print(json.dumps(payload, indent=2))


if __name__ == "__main__":
    main()
