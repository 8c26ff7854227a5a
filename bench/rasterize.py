"""Rasterizer speed and memory: cpp / torch / dense backends on a closed head-like surface.

Scene: N Gaussians on an ellipsoid of 0.08 × 0.11 × 0.10 m radii seen from 1 m, flat discs tangent to the
surface, sized so that about 28 Gaussians (both layers of the closed surface) reach each covered pixel with
α ≥ 1/255, as a UV-texel-per-Gaussian avatar gives. Sizes: 4,096 @ 128², 16,384 @ 256², 65,536 @ 512².

Each (backend, size) runs in its own process so its peak RSS is its own; times are medians after warm-up.
Writes ``bench/results/rasterize.json``. Usage: ``python bench/rasterize.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

SIZES = [(4096, 128), (16384, 256), (65536, 512)]
RADII = (0.08, 0.11, 0.10)
TARGET_DEPTH = 28.0
RESULTS = Path(__file__).resolve().parent / "results" / "rasterize.json"


def head_scene(n: int, size: int, seed: int = 0) -> dict:
    """Gaussians on an ellipsoid (Fibonacci lattice), one camera at 1 m looking down -z → rasterize kwargs."""
    generator = torch.Generator().manual_seed(seed)
    i = torch.arange(n, dtype=torch.float64) + 0.5
    polar = torch.acos(1 - 2 * i / n)
    azimuth = math.pi * (1 + 5**0.5) * i
    unit = torch.stack(
        [torch.sin(polar) * torch.cos(azimuth), torch.sin(polar) * torch.sin(azimuth), torch.cos(polar)], -1
    )
    radii = torch.tensor(RADII, dtype=torch.float64)
    means = unit * radii
    normals = torch.nn.functional.normalize(unit / radii, dim=-1)
    # Rotation taking +z to the normal (disc's thin axis along the normal).
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(normals)
    half = torch.nn.functional.normalize(
        z + normals + torch.tensor([1e-9, 0, 0], dtype=torch.float64), dim=-1
    )
    quats = torch.cat([(z * half).sum(-1, keepdim=True), torch.cross(z, half, dim=-1)], -1)
    area = (
        4
        * math.pi
        * ((RADII[0] * RADII[1]) ** 1.6 + (RADII[0] * RADII[2]) ** 1.6 + (RADII[1] * RADII[2]) ** 1.6)
        ** (1 / 1.6)
        / 3 ** (1 / 1.6)
    )
    opacities = 0.6 + 0.35 * torch.rand(n, generator=generator, dtype=torch.float64)
    # Footprint area with α ≥ 1/255 of a disc of std s: π s² 2 ln(255 o); two layers of the closed surface.
    footprint_per_s2 = math.pi * 2 * math.log(255 * 0.775)
    # 0.87: the sides of the surface are seen obliquely, which raises the overlap; measured to give ~28 deep.
    s = 0.87 * math.sqrt(TARGET_DEPTH / 2 * area / (n * footprint_per_s2))
    scales = torch.tensor([s, s, s * 0.1], dtype=torch.float64).expand(n, 3).clone()
    features = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    # Camera at world z = +1 looking at the origin: OpenCV axes x = world x, y = -world y, z = -world z.
    w2c = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    w2c[2, 3] = 1.0
    focal = 0.9 * size / (2 * 0.12)
    K = torch.tensor([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    f32 = {
        k: v.float()
        for k, v in dict(
            means=means,
            quats=quats,
            scales=scales,
            opacities=opacities,
            features=features,
            w2c=w2c[None],
            K=K[None],
        ).items()
    }
    return dict(**f32, width=size, height=size)


def measure_depth(scene: dict) -> tuple[float, float, int, int]:
    """Mean number of Gaussians with α ≥ 1/255 over covered pixels, covered fraction, kernel pixel evaluations
    (half rows over the chord, whole box rows) and Gaussian-tile intersections."""
    from relightanyone.render.rasterize_torch import (
        ALPHA_THRESHOLD,
        bin_gaussians_to_tiles,
        gaussian_alphas,
        project_gaussians,
    )

    proj = project_gaussians(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        scene["w2c"],
        scene["K"],
        scene["width"],
        scene["height"],
    )
    bins = bin_gaussians_to_tiles(proj.means2d, proj.radii, proj.depths, scene["width"], scene["height"])
    counts = torch.zeros(bins.tiles_y * 16, bins.tiles_x * 16)
    ids = bins.flatten_ids
    tile_of = torch.repeat_interleave(torch.arange(bins.tile_offsets.numel() - 1), bins.tile_offsets.diff())
    local = torch.arange(256)
    for start in range(0, ids.numel(), 4096):
        g, t = ids[start : start + 4096], tile_of[start : start + 4096]
        px = torch.stack(
            [(t % bins.tiles_x)[:, None] * 16 + local % 16, (t // bins.tiles_x)[:, None] * 16 + local // 16],
            -1,
        ).float()
        a, ok = gaussian_alphas(
            proj.means2d.reshape(-1, 2)[g][:, None],
            proj.conics.reshape(-1, 3)[g][:, None],
            proj.opacities.reshape(-1)[g][:, None],
            px,
        )
        hit = (ok & (a >= ALPHA_THRESHOLD)).float()
        counts.index_put_(
            (px[..., 1].long().reshape(-1), px[..., 0].long().reshape(-1)), hit.reshape(-1), accumulate=True
        )
    covered = counts > 0
    # Pixel evaluations of the compiled kernel: the rows of each Gaussian's box inside a tile (16 lanes per row
    # when whole rows are evaluated), and the 8-lane halves that overlap each row's alpha >= 1/255 chord (what
    # the kernel evaluates; same widened bound as render/csrc/rasterize_tiles.cpp).
    mean, ry = proj.means2d.reshape(-1, 2)[ids].double(), proj.radii.reshape(-1, 2)[ids].double()
    mx, my, rx, ry = mean[:, 0], mean[:, 1], ry[:, 0], ry[:, 1]
    camera_tile = tile_of % (bins.tiles_x * bins.tiles_y)
    col0, row0 = (camera_tile % bins.tiles_x * 16).double(), (camera_tile // bins.tiles_x * 16).double()
    box_y0 = torch.maximum(row0, torch.ceil(my - ry - 1))
    box_y1 = torch.minimum(row0 + 16, torch.floor(my + ry + 1) + 1)
    box_x0 = torch.maximum(col0, torch.ceil(mx - rx - 1))
    box_x1 = torch.minimum(col0 + 16, torch.floor(mx + rx + 1) + 1)
    whole_row_lanes = int((box_y1 - box_y0).clamp(min=0).sum()) * 16
    a, b, c = proj.conics.reshape(-1, 3)[ids].double().unbind(-1)
    limit = torch.log(255 * proj.opacities.reshape(-1)[ids].double())
    limit = limit + 1e-3 * limit.abs() + 1e-2
    y = row0[:, None] + torch.arange(16, dtype=torch.float64)
    dy = my[:, None] - y
    room = limit[:, None] - 0.5 * ((a * c - b * b) / a)[:, None] * dy**2
    half_width = torch.sqrt(room.clamp(min=0) * (2 / a)[:, None])
    centre = mx[:, None] + (b / a)[:, None] * dy
    x0 = torch.maximum(torch.ceil(centre - half_width) - 1, box_x0[:, None])
    x1 = torch.minimum(torch.floor(centre + half_width) + 2, box_x1[:, None])
    drawn = (room >= 0) & (x0 < x1) & (y >= box_y0[:, None]) & (y < box_y1[:, None])
    halves = torch.ceil((x1 - col0[:, None]) / 8) - torch.floor((x0 - col0[:, None]) / 8)
    lanes = int((halves * drawn).sum()) * 8
    return float(counts[covered].mean()), float(covered.float().mean()), lanes, whole_row_lanes, ids.numel()


def run_one(backend: str, n: int, size: int, reps: int) -> dict:
    """Time forward and forward+backward of one backend on one scene, in this process."""
    from relightanyone.render.rasterize import rasterize

    scene = head_scene(n, size)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    leaves = {
        k: scene[k].clone().requires_grad_(True)
        for k in ("means", "quats", "scales", "opacities", "features")
    }
    kwargs = {**scene, **leaves}

    def forward():
        with torch.no_grad():
            return rasterize(**kwargs, backend=backend)

    def forward_backward():
        out = rasterize(**kwargs, backend=backend)
        (out.features.sum() + out.alpha.sum() + out.depth.sum()).backward()
        for leaf in leaves.values():
            leaf.grad = None

    timings = {}
    for name, fn in (("forward", forward), ("forward_backward", forward_backward)):
        fn()  # warm-up (includes the one-time kernel load)
        wall, cpu = [], []
        for _ in range(reps):
            start, start_cpu = time.perf_counter(), time.process_time()
            fn()
            wall.append((time.perf_counter() - start) * 1e3)
            cpu.append((time.process_time() - start_cpu) * 1e3)
        timings[f"{name}_ms"] = round(statistics.median(wall), 2)
        # CPU time of all threads: robust when other work shares the machine (wall ≈ cpu / threads when idle)
        timings[f"{name}_cpu_ms"] = round(statistics.median(cpu), 2)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "backend": backend,
        "gaussians": n,
        "size": size,
        **timings,
        "reps": reps,
        "peak_rss_mb": round(peak / 1024, 1),
        "peak_rss_above_setup_mb": round((peak - base_rss) / 1024, 1),
    }


def matmul_gflops() -> float:
    """Measured float32 GEMM throughput of this machine (all threads): the arithmetic ceiling."""
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    start = time.perf_counter()
    for _ in range(5):
        a @ b
    return 5 * 2 * 2048**3 / (time.perf_counter() - start) / 1e9


def pair_count(n: int, size: int) -> dict:
    """Pixel-Gaussian pairs the cpp kernel evaluates (Gaussian boxes clipped to tiles) and contributing pairs."""
    depth, covered, lanes, whole_row_lanes, intersections = measure_depth(head_scene(n, size))
    return {
        "mean_depth_per_covered_pixel": round(depth, 2),
        "covered_fraction": round(covered, 3),
        "pixel_gaussian_pairs_alpha_above_1_255": int(depth * covered * size * size),
        "tile_intersections": intersections,
        "kernel_pixel_evaluations_per_pass": lanes,
        "pixel_evaluations_with_whole_box_rows": whole_row_lanes,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--one", nargs=3, metavar=("BACKEND", "N", "SIZE"))
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="no dense at 256²")
    parser.add_argument("--threads", type=int, default=0, help="torch/OpenMP threads (0: torch's default)")
    parser.add_argument(
        "--backends",
        default="cpp,torch,dense",
        help="comma-separated subset to (re)measure; other backends' runs are kept from the last file",
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]), int(args.one[2]), args.reps)))
        return

    load_at_start = [round(v, 2) for v in os.getloadavg()]
    runs = []
    plan = [("cpp", n, s, args.reps) for n, s in SIZES] + [
        ("torch", n, s, max(1, args.reps // 2)) for n, s in SIZES
    ]
    plan += [("dense", 4096, 128, 1)] + ([] if args.quick else [("dense", 16384, 256, 1)])
    wanted = set(args.backends.split(","))
    plan = [step for step in plan if step[0] in wanted]
    if RESULTS.exists() and wanted != {"cpp", "torch", "dense"}:
        runs = [run for run in json.loads(RESULTS.read_text())["runs"] if run["backend"] not in wanted]
    for backend, n, size, reps in plan:
        print(f"{backend:6s} {n:6d} @ {size}²", file=sys.stderr, flush=True)
        command = [sys.executable, __file__, "--one", backend, str(n), str(size), "--reps", str(reps)]
        out = subprocess.run(
            command + ["--threads", str(args.threads)], capture_output=True, text=True, check=True
        )
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print("   ", runs[-1], file=sys.stderr, flush=True)
    scenes = {f"{n}@{s}": pair_count(n, s) for n, s in SIZES}
    gflops = matmul_gflops()
    result = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpus": os.cpu_count(),
            "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
            "load_average_at_start": load_at_start,
            "load_average_at_end": [round(v, 2) for v in os.getloadavg()],
            "matmul_fp32_gflops": round(gflops, 1),
        },
        "scene": {
            "surface": f"ellipsoid radii {RADII} m at 1 m",
            "target_depth": TARGET_DEPTH,
            "per_size": scenes,
        },
        "runs": runs,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
