"""OLAT expansion measures: relit images per second (whole job, and rendering alone on decoded subjects),
fit time of unknown subjects, and peak memory.

Usage::

    python bench/expand.py [--source demo-out/aligned/ava256 --stage1 demo-out/runs/stage1
        --stage2 demo-out/runs/stage2]
        [--subjects 2|all] [--fit-iterations 10 5] [--workers 1] [--out bench-runs/expand]

The defaults are what ``make demo`` leaves in ``demo-out/``. Without trained runs at the given paths it builds the tiny sphere world of the tests (flat + OLAT datasets,
stage 1 and stage 2) and expands its flat dataset. Writes ``bench/results/expand.json`` with machine info and
the load average (the machine may be shared). CUDA numbers are measured only when CUDA is available.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "expand.json"
DEMO = Path(__file__).resolve().parent.parent / "demo-out"


def machine_info() -> dict:
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name(0)
        if torch.cuda.is_available()
        else "not available on this machine",
        "load_average_1_5_15_min": list(os.getloadavg()),
    }


def sphere_world(root: Path) -> tuple[Path, Path, Path]:
    """Build the tests' sphere world (flat=True) under ``root``: (flat dataset, stage-1 run, stage-2 run)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from helpers.sphere_world import build_sphere_world

    paths = build_sphere_world(root, flat=True)
    return paths["flat"], paths["stage1"], paths["stage2"]


def run_once(args, source: Path, stage1: Path, stage2: Path, device: str) -> dict:
    """One expansion in a fresh spawned process, so its peak memory is the expansion's alone."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_expand, args, source, stage1, stage2, device).result()


def _expand(args, source: Path, stage1: Path, stage2: Path, device: str) -> dict:
    import torch

    from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion

    torch.set_num_threads(1)  # what every expansion task uses

    out = Path(args.out) / device
    shutil.rmtree(out, ignore_errors=True)
    subjects = None
    if args.subjects != "all":
        from relightanyone.format.reader import NormalizedDataset

        subjects = NormalizedDataset(source).subjects[: int(args.subjects)]
    plan = plan_expansion(
        source,
        stage1,
        stage2,
        out,
        subjects=subjects,
        fit_iterations=tuple(args.fit_iterations),
        device=device,
    )
    start, cpu_start = time.perf_counter(), time.process_time()
    report = expand_dataset(plan, workers=args.workers, progress=False)
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
    images = report["counts"]["images"]
    decoded = [t for t in report["tasks"] if t["avatar"] == "decoded"]
    fitted = [t for t in report["tasks"] if t["avatar"] == "fitted"]
    first_view = plan.tasks[0].source_keys[0]
    from relightanyone.format.reader import NormalizedDataset

    row = NormalizedDataset(source).row(first_view)
    result = {
        "device": device,
        "source": str(source),
        "subjects": len(plan.tasks),
        "decoded_subjects": len(decoded),
        "fitted_subjects": len(fitted),
        "patterns": len(plan.patterns),
        "views": sum(len(t.source_keys) for t in plan.tasks),
        "image_size": [row.width, row.height],
        "images": images,
        "wall_s": round(seconds, 2),
        "images_per_s_whole_job": round(images / seconds, 2),
        # CPU seconds of the expansion process: less sensitive to other load on a shared machine.
        "cpu_s": round(cpu_seconds, 2),
        "images_per_cpu_s": round(images / cpu_seconds, 2) if args.workers == 1 else None,
    }
    if decoded:
        render_s = sum(t["seconds"] for t in decoded)
        result["images_per_s_render_only"] = round(sum(t["images"] for t in decoded) / render_s, 2)
    if fitted:
        result["fit_iterations"] = list(args.fit_iterations)
        result["seconds_per_fitted_subject"] = round(sum(t["seconds"] for t in fitted) / len(fitted), 2)
    # Peak of the expansion process (planning, model, fits, renders; pool workers when --workers > 1).
    result["peak_rss_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    if args.workers > 1:
        result["largest_worker_peak_rss_mib"] = round(
            resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0, 1
        )
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, default=DEMO / "aligned" / "ava256")
    parser.add_argument("--stage1", type=Path, default=DEMO / "runs" / "stage1")
    parser.add_argument("--stage2", type=Path, default=DEMO / "runs" / "stage2")
    parser.add_argument("--fit-iterations", type=int, nargs=2, default=[10, 5])
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument(
        "--subjects", default="2", help="how many source subjects to expand (first N), or 'all'"
    )
    parser.add_argument("--out", type=Path, default=None, help="scratch folder (default: a temporary one)")
    args = parser.parse_args(argv)

    import torch

    scratch = Path(tempfile.mkdtemp(prefix="bench-expand-"))
    args.out = args.out or scratch / "out"
    source, stage1, stage2 = args.source, args.stage1, args.stage2
    fixture = "given runs"
    if not all((p / "checkpoint.pt").is_file() for p in (stage1, stage2)) or not source.is_dir():
        print(f"no trained runs at {stage1} / {stage2}: building the sphere world", flush=True)
        source, stage1, stage2 = sphere_world(scratch / "world")
        fixture = "tests/sphere_world.py (built by this script)"
    runs = [run_once(args, source, stage1, stage2, "cpu")]
    if torch.cuda.is_available():
        runs.append(run_once(args, source, stage1, stage2, "cuda"))
    results = {
        "benchmark": "expand",
        "fixture": fixture,
        "workers": args.workers,
        "runs": runs,
        "machine": machine_info(),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    shutil.rmtree(scratch, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
