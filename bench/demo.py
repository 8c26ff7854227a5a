"""The demo end to end: cold (fresh output folder) and warm (everything skipped), per-stage times.

Usage::

    python bench/demo.py [--out bench-runs/demo] [--preset tiny] [--var name=value ...] [--keep]

Runs ``relightanyone run pipelines/demo.yaml`` twice with the same variables, reads every stage's
``_stage.json`` for its elapsed time, and writes ``bench/results/demo.json`` (machine info and the load
average included, since a shared machine slows everything). Goals: cold under 20 minutes, warm under 10 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "demo.json"
GOALS_S = {"cold": 20 * 60, "warm": 10}


def run_pipeline(out: Path, preset: str, extra_vars: list[str]) -> float:
    """Wall seconds of one ``relightanyone run`` of the demo pipeline (raises when it fails)."""
    command = [sys.executable, "-m", "relightanyone", "run", str(ROOT / "pipelines" / "demo.yaml"),
               "--var", f"out={out}", "--var", f"preset={preset}"]  # fmt: skip
    for assignment in extra_vars:
        command += ["--var", assignment]
    start = time.perf_counter()
    subprocess.run(command, check=True)
    return time.perf_counter() - start


def stage_times(out: Path) -> dict[str, float]:
    """{stage: elapsed seconds} from every ``_stage.json`` below ``out``."""
    times = {}
    for record_path in sorted(out.rglob("_stage.json")):
        record = json.loads(record_path.read_text())
        if "elapsed_s" in record:
            times[record["stage"]] = record["elapsed_s"]
    return dict(sorted(times.items(), key=lambda item: -item[1]))


def model_results(out: Path) -> dict:
    """Stage-1 held-out metrics and speed, the colour warm-up's with/without-matrix scores, and where the
    evaluation's JSON is (copied to ``bench/results/evaluation.json``)."""
    found = {}
    metrics = out / "runs" / "stage1" / "metrics.json"
    if metrics.is_file():
        values = json.loads(metrics.read_text())
        found["stage1"] = {
            k: values[k] for k in ("held_out", "seconds_per_iteration", "iterations") if k in values
        }
    alignment = out / "aligned" / "colour_alignment.json"
    if alignment.is_file():
        values = json.loads(alignment.read_text())
        found["colour_warmup"] = {
            k: values[k]
            for k in ("held_out_without_matrix", "held_out_with_colour_matrix", "held_out", "colour_matrices")
            if k in values
        }
    evaluation = out / "evaluation" / "evaluation.json"
    if evaluation.is_file():
        # Paths below the checkout are recorded relative to it, as every committed result is.
        (RESULTS.parent / "evaluation.json").write_text(evaluation.read_text().replace(f"{ROOT}/", ""))
        found["evaluation"] = "bench/results/evaluation.json"
    return found


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=ROOT / "bench-runs" / "demo")
    parser.add_argument("--preset", default="tiny", help="synthetic world preset (the make demo default)")
    parser.add_argument("--var", action="append", default=[], help="extra pipeline variable name=value")
    parser.add_argument("--keep", action="store_true", help="keep an existing output folder (not a cold run)")
    parser.add_argument(
        "--collect-only", action="store_true", help="only add the model results of --out to demo.json"
    )
    args = parser.parse_args()
    if args.collect_only:
        result = json.loads(RESULTS.read_text())
        result["models"] = model_results(args.out)
        RESULTS.write_text(json.dumps(result, indent=2) + "\n")
        return
    if args.out.exists() and not args.keep:
        shutil.rmtree(args.out)
    load_before = list(os.getloadavg())
    cold = run_pipeline(args.out, args.preset, args.var)
    warm = run_pipeline(args.out, args.preset, args.var)
    result = {
        "benchmark": "demo pipeline end to end",
        "pipeline": "pipelines/demo.yaml",
        "world_preset": args.preset,
        "vars": args.var,
        "cold_s": round(cold, 1),
        "warm_s": round(warm, 2),
        "goals_s": GOALS_S,
        "cold_goal_met": cold < GOALS_S["cold"],
        "warm_goal_met": warm < GOALS_S["warm"],
        "stage_seconds": stage_times(args.out),
        "models": model_results(args.out),
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "load_average_before_1_5_15_min": load_before,
            "load_average_after_1_5_15_min": list(os.getloadavg()),
        },
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("cold_s", "warm_s", "cold_goal_met", "warm_goal_met")}))


if __name__ == "__main__":
    main()
