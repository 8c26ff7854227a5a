"""Stage-1 measures on a normalized world: held-out PSNR/SSIM per dataset, the colour warm-up with and
without its learned matrix, how close that matrix is to the true colour cast, the lighting-code swap,
and the wall time per iteration.

Usage::

    python bench/stage1.py --root demo-out/normalized --answers demo-out/world/answers --preset tiny \
        --uncalibrated ava256 [--iterations N] [--warmup-iterations N] [--out bench-runs/stage1]

Writes ``bench/results/stage1.json`` (with machine info and the load average, since the machine may be
shared). The answers folder is read only here, to score the learned colour matrix.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "stage1.json"


def machine_info() -> dict:
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "load_average_1_5_15_min": list(os.getloadavg()),
    }


def true_casts(answers: Path, dataset_name: str) -> list[np.ndarray] | None:
    """Per-camera true colour responses of the synthetic dataset matching ``dataset_name`` (by dataset id
    or layout name in ``answers/*/truth.json``)."""
    for truth_path in sorted(Path(answers).glob("*/truth.json")):
        truth = json.loads(truth_path.read_text())
        if dataset_name in (truth.get("dataset"), truth.get("layout"), truth_path.parent.name):
            return [np.asarray(m, dtype=np.float64) for m in truth["colour_response"].values()]
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="folder of normalized datasets")
    parser.add_argument("--answers", type=Path, default=None, help="synthetic world answers/ folder")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--uncalibrated", action="append", default=[], help="dataset name (repeatable)")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--warmup-iterations", type=int, default=None)
    parser.add_argument(
        "--eval-views", type=int, default=None, help="held-out views per dataset (default all)"
    )
    parser.add_argument("--out", type=Path, default=Path("bench-runs/stage1"))
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (1 on a shared machine)")
    args = parser.parse_args(argv)

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)

    from relightanyone.format.shards import dataset_dirs
    from relightanyone.model.networks.presets import get_preset
    from relightanyone.model.train.colour_warmup import colour_cast_error, run_colour_warmup
    from relightanyone.model.train.run import lighting_alignment_grid, load_run
    from relightanyone.model.train.stage1 import Stage1Config, train_stage1

    data = dataset_dirs(args.root)
    if not data:
        print(f"{args.root}: no normalized datasets found; run ingest first", file=sys.stderr)
        return 1
    preset = get_preset(args.preset)
    changes = {
        k: v for k, v in (("iterations", args.iterations), ("warmup_iterations", args.warmup_iterations)) if v
    }
    preset = preset.replace(**changes) if changes else preset
    result: dict = {"benchmark": "stage 1", "preset": preset.to_json(), "datasets": [str(d) for d in data]}

    if args.uncalibrated:
        began = time.perf_counter()
        warm = run_colour_warmup(
            data, args.out, preset, tuple(args.uncalibrated), eval_views_per_dataset=args.eval_views
        )
        result["warmup"] = {
            "wall_seconds": time.perf_counter() - began,
            "seconds_per_iteration": warm["seconds_per_iteration"],
            "held_out_without_matrix": warm["held_out"],
            "held_out_with_matrix": warm["held_out_with_colour_matrix"],
            "learned_render_to_dataset": warm["colour_matrices"],
        }
        if args.answers:
            result["warmup"]["matrix_vs_truth"] = {
                name: colour_cast_error(np.asarray(matrix), casts)
                for name, matrix in warm["colour_matrices"].items()
                if (casts := true_casts(args.answers, name)) is not None
            }

    began = time.perf_counter()
    metrics = train_stage1(
        Stage1Config(data=data, out=args.out, preset=preset, eval_views_per_dataset=args.eval_views)
    )
    result["training"] = {
        "wall_seconds": time.perf_counter() - began,
        "seconds_per_iteration": metrics["seconds_per_iteration"],
        "held_out": metrics["held_out"],
    }
    run = load_run(args.out)
    result["lighting_swap"] = lighting_alignment_grid(run, args.out / "lighting_grid.png")
    shifts = [s["relative_colour_shift"] for s in result["lighting_swap"]["shifts"].values()]
    result["lighting_swap"]["mean_relative_colour_shift"] = float(np.mean(shifts)) if shifts else None
    result["lighting_swap"]["geometry_identical_everywhere"] = all(
        s["geometry_identical"] for s in result["lighting_swap"]["shifts"].values()
    )
    result["goal_psnr_db"] = 28.0
    result["goal_met"] = all(v["psnr"] >= 28.0 for v in metrics["held_out"].values())
    result["machine"] = machine_info()
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("training", "goal_met")}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
