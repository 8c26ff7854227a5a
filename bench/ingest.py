"""Ingest throughput and memory on the demo world (Ava-256 layout): writes bench/results/ingest.json.

Measures, in one run on the same images:

* ``bare_loop``: only decode + resize to the crop size + encode (with the shards' compression), one
  process, no files written, repeated ``BARE_PASSES`` times (one pass lasts about a second, too short to
  time steadily);
* ``end_to_end``: ``ingest_dataset`` (plan already made; alignment, decode, colour, undistort, crop, mask,
  encode, parts, commit) with 1 and 2 local workers, warm like the bare loop: a 2-subject ingest with the
  same workers runs first, so imports and the worker pool's server are not timed; the median of
  ``END_TO_END_REPEATS`` runs;
* ``cold``: the same runs in a fresh process, imports and pool start included (what one CLI call pays),
  the median of ``END_TO_END_REPEATS``;
* ``peak_memory``: peak RSS of a fresh process ingesting 2, 4, 8 ... subjects (it should stay flat);
* ``parallel_ceiling``: what the machine itself gives two processes: the bare loop in one fresh process,
  then in two at once; the ratio of their summed images per second to the single one (the median of
  three such pairs) is about the most two workers could reach over one;
* ``mask_methods``: milliseconds per mesh-silhouette mask, compiled depth buffer vs ray casting, at the
  crop sizes of the presets (the ingest uses the depth buffer);
* ``checks``: the convention checks' own CPU time (the checks without pixels and the image check of every
  view, decoding not counted: the tasks judge images they decode anyway) over the CPU time of a warm
  1-worker ingest of the same views in this process, ``checks_cost_fraction``; also per preset of
  ``full_size``, whose ``small`` preset (real image size, 512² crops) carries the goal (< 0.1):
  ``checks_cost_fraction_full_size``;
* ``full_size``: bare loop and warm 1-worker ingest of a smaller world whose Ava-256 images have the real
  dataset's size (667×1024), cropped to the ``small`` (512²) and ``paper`` (1024²) sizes: where the costs
  go when images are as large as real ones; also an undistorting bare loop, whose resize is the ingest's
  own undistort + crop + anti-aliased resize through each view's lens (the images are distorted, as real
  ones are): the ingest against the least a distorted rig needs.

Usage: ``python bench/ingest.py [--world DIR] [--full-size-world DIR] [--out bench/results/ingest.json]``;
the worlds are generated (Ava-256 only) when absent. ``--full-size-only small|paper`` measures only the
full-size world at that preset and prints it (nothing is written).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_WORLD = REPO / "demo-out" / "ingest-bench-world"
FULL_SIZE_WORLD = REPO / "demo-out" / "ingest-bench-world-full-size"
FULL_SIZE_PRESETS = ("small", "paper")
PRESET = "demo"
BARE_PASSES = 3
# Warm ingests of the demo world last 2-4 s, and single runs spread by ±10 %: the median of three is kept.
END_TO_END_REPEATS = 3


def repo_relative(path: Path) -> str:
    """``path`` as the results record it: relative to the checkout when inside it."""
    path = path.resolve()
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def ensure_world(world: Path) -> None:
    if (world / "world.json").is_file():
        return
    from relightanyone.progress import progress_bar
    from relightanyone.synth.world import generate_world

    print(f"generating the demo world (Ava-256 only) into {world} ...", flush=True)
    generate_world(world, "demo", seed=0, datasets=("d2",), progress=progress_bar, overwrite=True)


def ensure_full_size_world(world: Path) -> None:
    """4 Ava-256 subjects × 24 cameras at the real image size (667×1024), 1 frame, minimal answers."""
    if (world / "world.json").is_file():
        return
    import dataclasses

    from relightanyone.progress import progress_bar
    from relightanyone.synth.presets import PRESETS, DatasetSize
    from relightanyone.synth.world import generate_world

    size = DatasetSize(
        train_subjects=3, test_subjects=1, cameras=24, image_size=(667, 1024), frames=1, lights=2
    )
    preset = dataclasses.replace(
        PRESETS["demo"], name="demo-ava256-full-size", answer_lights=2, envmap_count=1, d2=size
    )
    print(f"generating the full-size Ava-256 world into {world} ...", flush=True)
    generate_world(world, preset, seed=0, datasets=("d2",), progress=progress_bar, overwrite=True, workers=2)


def mask_methods(world: Path, sizes=(128, 512, 1024), repeats: int = 5) -> dict:
    """Milliseconds per mesh-silhouette mask of the template, depth buffer vs rays, at each crop size.

    The camera frames the head the way the ingest's crop does (the projected head fills the crop with a
    10 % margin); the masks of both methods are compared pixel for pixel.
    """
    import numpy as np

    from relightanyone.ingest.steps import (
        MeshSilhouette,
        crop_box_around_points,
        crop_resize_intrinsics,
        project_points,
    )
    from relightanyone.ingest.tracking import load_template

    template = load_template(world / "answers" / "template" / "template.obj")
    vertices = template.vertices
    centre = vertices.mean(axis=0)
    eye = centre + [0.0, 0.0, 1.2]  # 1.2 m in front of the face (+z), looking back at it
    w2c = np.eye(4)
    w2c[:3, :3] = np.diag([1.0, -1.0, -1.0])  # OpenCV axes: x right, y down, z towards the head
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    K_source = np.array([[1200.0, 0.0, 511.5], [0.0, 1200.0, 511.5], [0.0, 0.0, 1.0]])
    box = crop_box_around_points(project_points(vertices[~template.neck_vertices], K_source, w2c), 1024)
    results = {}
    for size in sizes:
        K = crop_resize_intrinsics(K_source, box, size)
        row = {}
        masks = {}
        for method in ("depth-buffer", "rays"):
            silhouette = MeshSilhouette(vertices, template.faces, template.neck_faces, method=method)
            masks[method] = silhouette.mask(K, w2c, size)  # builds the ray structure or loads the kernel
            start = time.perf_counter()
            for _ in range(repeats):
                silhouette.mask(K, w2c, size)
            row[f"{method}_ms"] = round((time.perf_counter() - start) / repeats * 1000, 2)
        row["identical"] = bool(np.array_equal(masks["depth-buffer"], masks["rays"]))
        row["coverage"] = round(float(masks["rays"].mean()), 3)
        results[str(size)] = row
        print(f"mask {size}²: {row}", flush=True)
    return {"faces": int(template.faces.shape[0]), "sizes": results}


def full_size(world: Path, presets: tuple[str, ...] = FULL_SIZE_PRESETS) -> dict:
    """Bare loop and warm 1-worker ingest of the full-size world at each of ``presets``."""
    from relightanyone.ingest.runner import PRESET_SIZES

    ensure_full_size_world(world)
    plan = make_plan(world)
    runs = {}
    for preset in presets:
        bare = bare_loop(plan, PRESET_SIZES[preset])
        undistorting = bare_loop(plan, PRESET_SIZES[preset], undistort=True)
        one = warm_end_to_end(plan, world, 1, preset)
        runs[preset] = {
            "crop_size": PRESET_SIZES[preset],
            "bare_loop": bare,
            "undistorting_bare_loop": undistorting,
            "end_to_end_1_worker": one,
            "end_to_end_over_bare_loop": round(one["images_per_s"] / bare["images_per_s"], 3),
            "end_to_end_over_undistorting_bare_loop": round(
                one["images_per_s"] / undistorting["images_per_s"], 3
            ),
        }
        runs[preset]["checks"] = checks_cost(plan, world, preset)
        print(f"full size, {preset} crops: ratio {runs[preset]['end_to_end_over_bare_loop']}", flush=True)
    return {
        "world": repo_relative(world),
        "source_size": [667, 1024],
        "views": plan.view_count,
        "presets": runs,
    }


def make_plan(world: Path, subjects: int | None = None):
    from relightanyone.ingest import ava256
    from relightanyone.ingest.records import AdapterOptions

    plan = ava256.plan(world / "ava256", AdapterOptions())
    if subjects is not None:
        plan.subjects = sorted(plan.subjects, key=lambda s: s.subject)[:subjects]
    return plan


def bare_loop(plan, size: int, undistort: bool = False) -> dict:
    """Decode + resize + encode every view of ``plan`` in this process; images per second.

    Encode is what the format stores: the image in the default encoding and the mask PNG, under the
    shards' zstd (for the default ``raw-f16`` the compression is the encoding's only real work). Threads
    are set as an ingest task sets them (one for OpenCV and for the decoders), so both decode alike.
    With ``undistort``, the resize is the ingest's own undistort + crop + anti-aliased resize of the same
    square through the view's lens (no mask, valid pixels, checks or rows): the loop a distorted rig
    cannot do without.
    """
    import cv2
    import pyarrow as pa

    from relightanyone.format.arrow_io import ZSTD_LEVEL
    from relightanyone.format.codecs import encode_image, encode_mask
    from relightanyone.ingest.decode import TaskDecoder
    from relightanyone.ingest.steps import undistort_crop_resize
    from relightanyone.ingest.subject_task import configure_task_threads

    configure_task_threads()  # one AVIF thread, as in the tasks; videos are not timed here
    codec = pa.Codec("zstd", compression_level=ZSTD_LEVEL)
    views = [v for s in plan.subjects for v in s.views]
    with TaskDecoder(plan.source_root) as decoder:  # warm the imports and caches on one view
        image, _ = decoder.decode(views[0].image)
        codec.compress(encode_image(cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)))
    start = time.perf_counter()
    for _ in range(BARE_PASSES):
        with TaskDecoder(plan.source_root) as decoder:
            for view in views:
                image, _ = decoder.decode(view.image)
                side = min(image.shape[:2])
                if undistort:
                    box = (0, 0, side, side)
                    resized, _ = undistort_crop_resize(image, view.camera.K, view.camera.dist, box, size)
                else:
                    resized = cv2.resize(image[:side, :side], (size, size), interpolation=cv2.INTER_AREA)
                codec.compress(encode_image(resized))
                codec.compress(encode_mask(resized[:, :, 0] > 0.01))
    seconds = time.perf_counter() - start
    return {
        "undistorts": undistort,
        "passes": BARE_PASSES,
        "images": len(views) * BARE_PASSES,
        "seconds": round(seconds, 3),
        "images_per_s": round(len(views) * BARE_PASSES / seconds, 2),
    }


def bare_child(world: Path, start_at: float) -> None:
    """Run in a fresh process: wait until ``start_at`` (a ``time.time()``), run the bare loop, print it."""
    plan = make_plan(world)
    time.sleep(max(0.0, start_at - time.time()))
    print(json.dumps(bare_loop(plan, _crop_size())))


def _crop_size() -> int:
    from relightanyone.ingest.runner import PRESET_SIZES

    return PRESET_SIZES[PRESET]


def parallel_ceiling(world: Path, processes: int = 2, repeats: int = END_TO_END_REPEATS) -> dict:
    """Images per second of the bare loop in one fresh process, then in ``processes`` at once (started
    together once their imports are done), and the ratio of the latter's sum to the former; the median
    ratio of ``repeats`` such pairs, since single runs on a shared machine spread widely."""

    def run(count: int) -> list[dict]:
        start_at = time.time() + 10.0  # imports and planning take a few seconds per process
        children = [
            subprocess.Popen(
                [sys.executable, __file__, "--world", str(world), "--bare-child", str(start_at)],
                stdout=subprocess.PIPE,
                text=True,
            )
            for _ in range(count)
        ]
        outputs = [child.communicate()[0] for child in children]
        if any(child.returncode for child in children):
            raise RuntimeError("a bare-loop child process failed")
        return [json.loads(out.strip().splitlines()[-1]) for out in outputs]

    pairs = []
    for _ in range(repeats):
        alone = run(1)[0]["images_per_s"]
        together = [r["images_per_s"] for r in run(processes)]
        pairs.append(
            {
                "one_process_images_per_s": alone,
                "each_process_images_per_s": together,
                "sum_over_one": round(sum(together) / alone, 3),
            }
        )
    return {"processes": processes, **median_run(pairs, "sum_over_one")}


def end_to_end(plan, world: Path, workers: int, preset: str = PRESET) -> dict:
    from relightanyone.ingest.runner import ingest_dataset

    with tempfile.TemporaryDirectory(prefix="ingest-bench-") as out:
        start = time.perf_counter()
        summary = ingest_dataset(
            plan,
            world / "tracking" / "d2",
            Path(out),
            preset,
            workers=workers,
            progress=False,
            template=world / "answers" / "template" / "template.obj",
        )
        seconds = time.perf_counter() - start
    return {
        "workers": workers,
        "images": summary.rows,
        "quarantined": summary.quarantined,
        "seconds": round(seconds, 3),
        "images_per_s": round(summary.rows / seconds, 2),
    }


def warm_end_to_end(plan, world: Path, workers: int, preset: str = PRESET, repeats: int = 1) -> dict:
    """:func:`end_to_end` after a 2-subject ingest with the same workers (imports, pool server); with
    ``repeats`` > 1, the run of median time, with every run's seconds."""
    warm_plan = make_plan(world, 2)
    end_to_end(warm_plan, world, workers, preset)
    runs = [end_to_end(plan, world, workers, preset) for _ in range(repeats)]
    return median_run(runs, "seconds") if repeats > 1 else runs[0]


def checks_cost(plan, world: Path, preset: str = PRESET) -> dict:
    """CPU seconds of the convention checks on ``plan`` against the CPU seconds of its 1-worker ingest (in
    this process, warm), both measured on the same views: the checks without pixels (run once, before
    writing) plus the image check of every view (run by the tasks on images they decode anyway, so
    decoding is not counted). CPU time, not wall time: on a loaded machine the wall time of a short step
    mostly measures the other processes."""
    from relightanyone.ingest.checks import check_tasks, view_item
    from relightanyone.ingest.decode import TaskDecoder
    from relightanyone.ingest.image_decisions import ImageCheck
    from relightanyone.ingest.runner import ingest_dataset, prepare
    from relightanyone.ingest.subject_task import FrameMesh, canonical_mesh

    template_path = world / "answers" / "template" / "template.obj"
    tracking = world / "tracking" / "d2"
    with tempfile.TemporaryDirectory(prefix="ingest-bench-") as out:
        ingest_dataset(plan, tracking, Path(out) / "warm", preset, progress=False, template=template_path)
        start = time.process_time()
        ingest_dataset(plan, tracking, Path(out) / "timed", preset, progress=False, template=template_path)
        ingest_cpu = time.process_time() - start
    _, template, tasks = prepare(plan, tracking, preset, template_path)
    start = time.process_time()
    report = check_tasks(tasks, template)
    without_pixels = time.process_time() - start
    images = 0.0
    for task in tasks:
        with TaskDecoder(plan.source_root) as decoder:
            decoded = [(view, decoder.decode(view.image)[0]) for view in task.plan.views]
        # The frames' silhouettes are the task's own (it masks every row with them): not a cost of the checks.
        silhouettes = {
            frame: FrameMesh.from_vertices(canonical_mesh(alignment, template), template).silhouette
            for frame, alignment in task.alignments.items()
        }
        start = time.process_time()
        check = ImageCheck(task, silhouettes)
        for view, image in decoded:
            check.holds(view, view_item(view), image)
        check.decide()
        images += time.process_time() - start
    return {
        "views": plan.view_count,
        "findings": len(report.findings),
        "cpu_seconds_without_pixels": round(without_pixels, 4),
        "cpu_seconds_image_check": round(images, 4),
        "cpu_seconds_ingest": round(ingest_cpu, 4),
        "checks_cost_fraction": round((without_pixels + images) / ingest_cpu, 4),
    }


def median_run(runs: list[dict], key: str) -> dict:
    """The run of median ``key``, with every run's ``key`` under ``<key>_of_every_run`` (sorted)."""
    ordered = sorted(runs, key=lambda r: r[key])
    median = dict(ordered[len(ordered) // 2])
    median[f"{key}_of_every_run"] = [r[key] for r in ordered]
    return median


def child_run(world: Path, subjects: int, workers: int) -> None:
    """Run in a fresh process: ingest ``subjects`` subjects cold and print the result with peak RSS.

    Like the ``ingest`` command, it starts the worker pool before planning (``Executor.warm``)."""
    start = time.perf_counter()
    from relightanyone.ingest.runner import ingest_executor

    ingest_executor(workers).warm()
    plan = make_plan(world, subjects)
    result = end_to_end(plan, world, workers)
    result["seconds_with_imports"] = round(time.perf_counter() - start, 3)
    result["subjects"] = subjects
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(json.dumps(result))


def in_fresh_process(world: Path, subjects: int, workers: int) -> dict:
    output = subprocess.run(
        [sys.executable, __file__, "--world", str(world), "--child", str(subjects), str(workers)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return json.loads(output.strip().splitlines()[-1])


def cold_run(world: Path, subjects: int, workers: int) -> dict:
    """The median (by time with imports) of ``END_TO_END_REPEATS`` cold runs in fresh processes."""
    runs = [in_fresh_process(world, subjects, workers) for _ in range(END_TO_END_REPEATS)]
    return median_run(runs, "seconds_with_imports")


def peak_memory(world: Path, counts: list[int]) -> list[dict]:
    rows = []
    for count in counts:
        rows.append(in_fresh_process(world, count, 1))
        print(f"  {count} subjects: peak RSS {rows[-1]['peak_rss_mb']} MB", flush=True)
    return rows


def machine() -> dict:
    import numpy

    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "load_average_1_5_15_min_at_end": list(os.getloadavg()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, default=DEFAULT_WORLD)
    parser.add_argument("--full-size-world", type=Path, default=FULL_SIZE_WORLD)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "ingest.json")
    parser.add_argument(
        "--checks-only",
        action="store_true",
        help="measure only the bare loop, the 1-worker ingest and the checks' cost; write nothing",
    )
    parser.add_argument(
        "--full-size-only",
        choices=FULL_SIZE_PRESETS,
        default=None,
        help="measure only the full-size world's bare loop, ingest and checks at this preset; write nothing",
    )
    parser.add_argument("--child", type=int, nargs=2, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--bare-child", type=float, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        child_run(args.world, *args.child)
        return
    if args.bare_child is not None:
        bare_child(args.world, args.bare_child)
        return
    if args.full_size_only is not None:
        print(json.dumps(full_size(args.full_size_world, (args.full_size_only,)), indent=2))
        return
    from relightanyone.ingest.runner import PRESET_SIZES

    ensure_world(args.world)
    plan = make_plan(args.world)
    size = PRESET_SIZES[PRESET]
    print(f"{plan.view_count} views of {len(plan.subjects)} subjects, crops {size}²", flush=True)
    bare = bare_loop(plan, size)
    print(f"bare loop: {bare['images_per_s']} images/s", flush=True)
    one = warm_end_to_end(plan, args.world, 1, repeats=END_TO_END_REPEATS)
    print(f"end to end, 1 worker: {one['images_per_s']} images/s", flush=True)
    checks = checks_cost(plan, args.world)
    print(f"convention checks: {checks['checks_cost_fraction']} of the ingest's time", flush=True)
    if args.checks_only:
        print(json.dumps(checks, indent=2))
        return
    two = warm_end_to_end(plan, args.world, 2, repeats=END_TO_END_REPEATS)
    print(f"end to end, 2 workers: {two['images_per_s']} images/s", flush=True)
    subjects = len(plan.subjects)
    cold = [cold_run(args.world, subjects, workers) for workers in (1, 2)]
    for run in cold:
        print(f"cold, {run['workers']} worker(s): {run['seconds_with_imports']} s with imports", flush=True)
    ceiling = parallel_ceiling(args.world)
    print(f"bare loop in 2 processes at once: {ceiling['sum_over_one']}× one", flush=True)
    counts = sorted({c for c in (2, 4, 8, 16) if c <= subjects} | {subjects})
    memory = peak_memory(args.world, counts)
    masks = mask_methods(args.world)
    large = full_size(args.full_size_world)
    result = {
        "benchmark": "ingest throughput (Ava-256 layout of the demo world)",
        "world": {
            "path": repo_relative(args.world),
            "preset": PRESET,
            "subjects": subjects,
            "views": plan.view_count,
            "crop_size": size,
        },
        "machine": machine(),
        "bare_loop": bare,
        "end_to_end": [one, two],
        "cold": cold,
        "ratios": {
            "end_to_end_1_worker_over_bare_loop": round(one["images_per_s"] / bare["images_per_s"], 3),
            "goal_end_to_end_over_bare_loop": round(1 / 1.3, 3),
            "two_workers_over_one": round(two["images_per_s"] / one["images_per_s"], 3),
            "goal_two_workers_over_one": 1.7,
            "bare_loop_two_processes_over_one": ceiling["sum_over_one"],
            "checks_cost_fraction": checks["checks_cost_fraction"],
            # The goal's size: real Ava-256 images (667×1024) cropped to 512² (`small`).
            "checks_cost_fraction_full_size": large["presets"]["small"]["checks"]["checks_cost_fraction"],
            "goal_checks_cost_fraction": 0.1,
            "end_to_end_1_worker_over_bare_loop_full_size": {
                preset: run["end_to_end_over_bare_loop"] for preset, run in large["presets"].items()
            },
            "end_to_end_1_worker_over_undistorting_bare_loop_full_size": {
                preset: run["end_to_end_over_undistorting_bare_loop"]
                for preset, run in large["presets"].items()
            },
            "cold_two_workers_over_one": round(
                cold[0]["seconds_with_imports"] / cold[1]["seconds_with_imports"], 3
            ),
        },
        "checks": checks,
        "parallel_ceiling": ceiling,
        "peak_memory": memory,
        "mask_methods": masks,
        "full_size": large,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["ratios"], indent=2))


if __name__ == "__main__":
    main()
