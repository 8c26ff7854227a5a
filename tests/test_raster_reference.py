"""Rasterizer backends against the dense reference (scenes from ``helpers.raster_scenes``)."""

from __future__ import annotations

import pytest
import torch
from helpers.raster_scenes import (
    GAUSSIAN_INPUTS,
    assert_close,
    project_scene,
    random_scene,
    render_with_grads,
)

from relightanyone.render.rasterize import rasterize
from relightanyone.render.rasterize_cpp import tile_kernel_available

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# --------------------------------------------------------------------------------------------------------
# Reference checks: tiled backends against the dense every-pixel × every-Gaussian oracle.

needs_kernel = pytest.mark.skipif(
    not tile_kernel_available(), reason="C++ rasterizer kernel could not be built"
)


SCENES = {
    "plain": dict(seed=0),
    "per-camera-features-5ch": dict(seed=3, channels=5, per_camera_features=True),
    "opaque-deep": dict(seed=5, n=120, opacity_range=(0.6, 1.0), scale_range=(0.03, 0.08)),
}


# backend -> (dtype it renders in, tolerance against the float64 dense reference)
BACKENDS = {"torch": (torch.float64, 1e-10), "cpp": (torch.float32, 1e-5)}


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("name", list(SCENES))
@pytest.mark.parametrize("backend", ["torch", pytest.param("cpp", marks=needs_kernel)])
def test_tiled_backend_matches_dense_reference(backend, name, mode):
    dtype, tol = BACKENDS[backend]
    scene = random_scene(**SCENES[name])
    background = torch.linspace(0.1, 0.4, scene["features"].shape[-1], dtype=torch.float64)
    ref_out, ref_grads = render_with_grads(scene, "dense", torch.float64, mode=mode, background=background)
    out, grads = render_with_grads(scene, backend, dtype, mode=mode, background=background.to(dtype))
    assert float(ref_out[1].max()) > 0.5, "scene should cover part of the image"
    for label, a, b in zip(("features", "alpha", "depth"), out, ref_out, strict=True):
        assert_close(a, b, tol, label)
    for key in GAUSSIAN_INPUTS:
        assert_close(grads[key], ref_grads[key], tol, f"d/d{key}")


def test_opaque_scene_exercises_cap_and_early_stop():
    """The deep scene must hit the 0.999 cap and stop early somewhere, or the test above proves less."""
    scene = random_scene(**SCENES["opaque-deep"])
    out, _ = render_with_grads(scene, "dense", torch.float64)
    assert float(out[1].max()) > 1 - 1e-3  # transmittance reached the stop threshold region
    proj = project_scene(scene)
    assert float(proj.opacities.max()) > 0.999


def test_gradcheck_torch_backend_float64():
    scene = random_scene(n=4, cameras=1, width=11, height=9, seed=7, scale_range=(0.02, 0.05))
    names = GAUSSIAN_INPUTS
    inputs = tuple(scene[k].clone().requires_grad_(True) for k in names)

    def render(*tensors):
        kwargs = dict(zip(names, tensors, strict=True))
        out = rasterize(
            **kwargs,
            w2c=scene["w2c"],
            K=scene["K"],
            width=11,
            height=9,
            backend="torch",
            background=torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64),
        )
        return out.features, out.alpha, out.depth

    assert float(render(*inputs)[1].detach().max()) > 0.3
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradcheck_antialiased_mode_float64():
    scene = random_scene(n=3, cameras=1, width=9, height=8, seed=11, scale_range=(0.01, 0.03))
    inputs = tuple(scene[k].clone().requires_grad_(True) for k in ("means", "scales", "opacities"))

    def render(means, scales, opacities):
        out = rasterize(
            means,
            scene["quats"],
            scales,
            opacities,
            scene["features"],
            scene["w2c"],
            scene["K"],
            9,
            8,
            mode="antialiased",
            backend="torch",
        )
        return out.features, out.alpha

    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
