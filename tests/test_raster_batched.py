"""``rasterize_batched``: B Gaussian sets into their own cameras in one call, equal to B separate calls;
and the value checks that read back to the host are skipped for GPU tensors unless switched on."""

from __future__ import annotations

import pytest
import torch
from helpers.raster_scenes import GAUSSIAN_INPUTS, random_scene

from relightanyone.render import rasterize as rasterize_module
from relightanyone.render.rasterize import rasterize, rasterize_batched, set_value_checks

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _batch(count: int):
    scenes = [
        random_scene(n=120, cameras=2, width=40, height=30, seed=seed, dtype=torch.float32)
        for seed in range(count)
    ]
    stacked = {key: torch.stack([scene[key] for scene in scenes]) for key in (*GAUSSIAN_INPUTS, "w2c", "K")}
    return scenes, stacked


@pytest.mark.parametrize("background", [None, torch.tensor([0.2, 0.1, 0.3])])
def test_batched_equals_one_call_per_set(background):
    scenes, stacked = _batch(3)
    batched = rasterize_batched(
        stacked["means"],
        stacked["quats"],
        stacked["scales"],
        stacked["opacities"],
        stacked["features"],
        stacked["w2c"],
        stacked["K"],
        40,
        30,
        background=background,
    )
    assert batched.features.shape == (3, 2, 3, 30, 40) and batched.alpha.shape == (3, 2, 1, 30, 40)
    for index, scene in enumerate(scenes):
        single = rasterize(
            *(scene[key] for key in (*GAUSSIAN_INPUTS, "w2c", "K")), 40, 30, background=background
        )
        for part, alone in zip(batched, single, strict=True):
            assert torch.equal(part[index], alone)


def test_batched_needs_one_camera_set_per_gaussian_set():
    _, stacked = _batch(2)
    with pytest.raises(ValueError, match="must share B"):
        rasterize_batched(
            *(stacked[key] for key in GAUSSIAN_INPUTS), stacked["w2c"][:1], stacked["K"][:1], 40, 30
        )


def test_value_checks_run_on_the_cpu_and_on_a_gpu_only_when_switched_on():
    gpu_like = torch.empty(3, device="meta")  # stands in for a CUDA tensor: not on the host
    assert rasterize_module._checks_values(torch.zeros(3))
    assert not rasterize_module._checks_values(gpu_like)
    set_value_checks(True)
    try:
        assert rasterize_module._checks_values(gpu_like)
    finally:
        set_value_checks(False)
