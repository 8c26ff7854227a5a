"""Ingest throughput through an existing Ray cluster with 1 and 2 worker nodes: writes bench/results/ray.json.

A head node with no CPUs of its own and N one-CPU worker nodes are started with ``ray start`` (as a lab
starts them on its machines); a synthetic world's Ava-256 capture (``--world-preset``, default ``tiny``)
is ingested through the cluster with
``--executor ray`` joined by address, after a 2-subject warm-up run on the same cluster (so worker start
and imports are not timed). The ratio of 2 nodes to 1 is the speed-up a second machine's worker gives;
on this 2-core machine it is bounded by what two processes get at once (``parallel_ceiling`` in
bench/results/ingest.json) and by the load of the machine, which is recorded.

Usage: ``python bench/ray_executor.py [--world DIR] [--world-preset tiny|demo] [--out bench/results/ray.json]
[--repeats N]``; the world is generated (Ava-256 only) when absent.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests"))

from ingest import REPO, machine, make_plan  # noqa: E402  (bench/ingest.py)

DEFAULT_WORLD = REPO / "demo-out" / "ray-bench-world"

GOAL_TWO_OVER_ONE = 1.7


def ensure_world(world: Path, preset: str) -> None:
    if (world / "world.json").is_file():
        return
    from relightanyone.progress import progress_bar
    from relightanyone.synth.world import generate_world

    print(f"generating the {preset} world (Ava-256 only) into {world} ...", flush=True)
    generate_world(world, preset, seed=0, datasets=("d2",), progress=progress_bar, overwrite=True, workers=2)


def ingest_through(address: str, plan, world: Path, out: Path, workers: int) -> dict:
    """One ingest of ``plan`` through the cluster at ``address``: rows, seconds, images per second."""
    from relightanyone.ingest.runner import ingest_dataset

    os.environ["RAY_ADDRESS"] = address
    start = time.perf_counter()
    summary = ingest_dataset(
        plan,
        world / "tracking" / "d2",
        out,
        "demo",
        workers=workers,
        executor="ray",
        progress=False,
        template=world / "answers" / "template" / "template.obj",
    )
    seconds = time.perf_counter() - start
    return {
        "images": summary.rows,
        "seconds": round(seconds, 3),
        "images_per_s": round(summary.rows / seconds, 2),
    }


def cluster_run(world: Path, nodes: int, repeats: int, scratch: Path) -> dict:
    import ray
    from helpers.ray_cluster import ray_cluster

    plan, warm_plan = make_plan(world), make_plan(world, subjects=2)
    with ray_cluster(worker_nodes=nodes, cpus_per_node=1, head_cpus=0) as address:
        try:
            ingest_through(address, warm_plan, world, scratch / f"warm-{nodes}", nodes)
            runs = [
                ingest_through(address, plan, world, scratch / f"run-{nodes}-{k}", nodes)
                for k in range(repeats)
            ]
            cpus = ray.cluster_resources().get("CPU", 0)
        finally:
            ray.shutdown()
    best = statistics.median(run["images_per_s"] for run in runs)
    print(f"{nodes} worker node(s): {best} images/s (runs {[r['images_per_s'] for r in runs]})", flush=True)
    return {"worker_nodes": nodes, "cluster_cpus": cpus, "runs": runs, "median_images_per_s": best}


def main() -> None:
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, default=DEFAULT_WORLD)
    parser.add_argument("--world-preset", default="tiny", choices=("tiny", "demo"))
    parser.add_argument("--out", type=Path, default=BENCH / "results" / "ray.json")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    ensure_world(args.world, args.world_preset)
    load_at_start = list(os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="ray-bench-") as scratch:
        one, two = (cluster_run(args.world, nodes, args.repeats, Path(scratch)) for nodes in (1, 2))
    ratio = round(two["median_images_per_s"] / one["median_images_per_s"], 3)
    result = {
        "world_preset": args.world_preset,
        "what": "Ava-256 ingest of a synthetic world through a Ray cluster joined by address (head 0 CPUs, 1-CPU worker nodes)",
        "one_worker_node": one,
        "two_worker_nodes": two,
        "two_over_one": ratio,
        "goal_two_over_one": GOAL_TWO_OVER_ONE,
        "goal_met": ratio >= GOAL_TWO_OVER_ONE,
        "load_average_1_5_15_min_at_start": load_at_start,
        "machine": machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"2 nodes / 1 node: {ratio} (goal {GOAL_TWO_OVER_ONE}); written to {args.out}", flush=True)


if __name__ == "__main__":
    main()
