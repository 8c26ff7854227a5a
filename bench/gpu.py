"""Training speed and peak memory on a GPU, per preset: writes ``bench/results/gpu.json``.

For each preset, one synthetic training step of stage 1 (fp32) and of stage 2 (fp32, and bf16 with
checkpointed maps) on the planning template (every UV texel a Gaussian, ring cameras, a rig of
``--lights`` lights): iterations per second over ``--iterations`` timed steps after two warm-up steps, the
peak of ``torch.cuda.max_memory_allocated`` and the estimate of ``relightanyone plan`` beside it. A step
that runs out of memory is recorded as such.

Without CUDA it records that no GPU was available and exits 0.

Usage::

    python bench/gpu.py [--presets tiny,small,paper] [--iterations 10] [--lights 150]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import torch

from relightanyone.model.networks.presets import get_preset, get_stage2_preset
from relightanyone.model.train.memory import (
    GIB,
    StepShape,
    estimate_stage1,
    estimate_stage2,
    planning_models,
    stage1_step_loss,
    stage2_step_loss,
)

RESULTS = Path(__file__).resolve().parent / "results" / "gpu.json"


def machine_info() -> dict:
    info = {
        "platform": platform.platform(),
        "torch": torch.__version__,
        "load_average_1_5_15_min": list(os.getloadavg()),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
        info["gpu_memory_gib"] = round(torch.cuda.get_device_properties(0).total_memory / GIB, 1)
        try:
            import gsplat

            info["gsplat"] = gsplat.__version__
        except ImportError:
            info["gsplat"] = None
    return info


def timed_steps(loss_fn, trained: torch.nn.Module, iterations: int) -> dict:
    """Iterations per second and peak GPU memory of Adam steps on ``loss_fn``."""
    optimizer = torch.optim.Adam([p for p in trained.parameters() if p.requires_grad], lr=1e-4)

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        loss_fn().backward()
        optimizer.step()

    torch.cuda.reset_peak_memory_stats()
    try:
        for _ in range(2):
            step()
        torch.cuda.synchronize()
        began = time.perf_counter()
        for _ in range(iterations):
            step()
        torch.cuda.synchronize()
        seconds = time.perf_counter() - began
    except torch.OutOfMemoryError:
        return {"out_of_memory": True}
    finally:
        optimizer.zero_grad(set_to_none=True)
    return {
        "iterations_per_second": round(iterations / seconds, 3),
        "peak_gib": round(torch.cuda.max_memory_allocated() / GIB, 3),
    }


def bench_preset(name: str, iterations: int, lights: int) -> dict:
    preset, stage2_preset = get_preset(name), get_stage2_preset(name)
    stage1, stage2 = planning_models(preset, stage2_preset)
    stage1, stage2 = stage1.cuda(), stage2.cuda()
    shape1 = StepShape(preset.batch_size, preset.crop_size)
    shape2 = StepShape(stage2_preset.batch_size, stage2_preset.crop_size, lights)
    results = {"gaussians": stage1.gaussian_count, "stage1": {}, "stage2": {}}
    stage1.precision = "fp32"
    results["stage1"]["fp32"] = timed_steps(stage1_step_loss(stage1, shape1), stage1, iterations) | {
        "estimated_gib": round(estimate_stage1(stage1, shape1)["total"] / GIB, 3)
    }
    for precision, checkpointed in (("fp32", False), ("bf16", True)):
        stage2.precision, stage2.checkpoint_maps = precision, checkpointed
        key = precision + ("+checkpointing" if checkpointed else "")
        measured = timed_steps(stage2_step_loss(stage1, stage2, shape2), stage2, iterations)
        estimate = estimate_stage2(stage1, stage2, shape2, precision, checkpointed)["total"]
        results["stage2"][key] = measured | {"estimated_gib": round(estimate / GIB, 3)}
        torch.cuda.empty_cache()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default="tiny,small,paper")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--lights", type=int, default=150)
    args = parser.parse_args()
    payload = {"machine": machine_info(), "iterations": args.iterations, "lights": args.lights}
    if not torch.cuda.is_available():
        payload["gpu"] = None
        payload["note"] = "no GPU was available: nothing was measured"
        print(payload["note"])
    else:
        payload["presets"] = {}
        for name in args.presets.split(","):
            payload["presets"][name] = bench_preset(name, args.iterations, args.lights)
            print(name, json.dumps(payload["presets"][name]))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
