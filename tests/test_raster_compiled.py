"""The compiled kernel's own parts: tile binning against the PyTorch binning, thin ellipses (the per-row
column narrowing) against the dense reference, and independence of the thread count."""

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
from relightanyone.render.rasterize_cpp import (
    bin_gaussians_to_tiles_cpp,
    project_gaussians_cpp,
    tile_kernel_available,
)
from relightanyone.render.rasterize_torch import bin_gaussians_to_tiles, project_gaussians

pytestmark = pytest.mark.skipif(
    not tile_kernel_available(), reason="C++ rasterizer kernel could not be built"
)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_binning_equals_torch_binning(dtype):
    scene = random_scene(
        n=300, cameras=2, width=70, height=50, seed=9, dtype=dtype, scale_range=(0.005, 0.08)
    )
    scene["means"][:5, 0] += 0.8  # some Gaussians off screen
    proj = project_scene(scene)
    depths = proj.depths.clone()
    depths[:, 10:40] = depths[:, 10:11]  # ties in depth must keep the Gaussian order
    expected = bin_gaussians_to_tiles(proj.means2d, proj.radii, depths, 70, 50, tile_size=16)
    actual = bin_gaussians_to_tiles_cpp(proj.means2d, proj.radii, depths, 70, 50, tile_size=16)
    assert expected.flatten_ids.numel() > 1000
    assert torch.equal(actual.tile_offsets, expected.tile_offsets)
    assert torch.equal(actual.flatten_ids, expected.flatten_ids)
    assert (actual.tiles_x, actual.tiles_y, actual.tile_size) == (expected.tiles_x, expected.tiles_y, 16)


def test_compiled_binning_of_nothing_visible():
    means2d = torch.zeros(2, 3, 2)
    bins = bin_gaussians_to_tiles_cpp(
        means2d, torch.zeros(2, 3, 2, dtype=torch.int32), torch.ones(2, 3), 40, 20
    )
    assert bins.flatten_ids.numel() == 0
    assert bins.tile_offsets.shape == (2 * 3 * 2 + 1,) and int(bins.tile_offsets.abs().max()) == 0


def needle_scene(seed: int) -> dict:
    """Long thin Gaussians at random orientations: screen ellipses with a condition number in the thousands."""
    scene = random_scene(n=60, cameras=2, width=45, height=38, seed=seed, opacity_range=(0.3, 1.0))
    g = torch.Generator().manual_seed(seed + 100)
    long_axis = 0.02 + 0.1 * torch.rand(60, generator=g, dtype=torch.float64)
    scene["scales"] = (
        torch.stack(
            [
                long_axis,
                0.0005 + 0.001 * torch.rand(60, generator=g, dtype=torch.float64),
                torch.full((60,), 0.001, dtype=torch.float64),
            ],
            -1,
        )
        .float()
        .double()
    )
    return scene


@pytest.mark.parametrize("seed", [1, 2])
def test_cpp_thin_ellipses_match_dense_reference(seed):
    # classic mode only: the antialiased compensation of a needle, det(Σ₂) / det(Σ₂ + 0.3 I), cancels badly in
    # float32 (the float32 torch backend is off by 3e-3 as well), which says nothing about the compositor.
    scene = needle_scene(seed)
    ref_out, ref_grads = render_with_grads(scene, "dense", torch.float64)
    out, grads = render_with_grads(scene, "cpp", torch.float32)
    assert float(ref_out[1].max()) > 0.5
    for label, a, b in zip(("features", "alpha", "depth"), out, ref_out, strict=True):
        assert_close(a, b, 1e-5, label)
    # Needle shapes make float32 gradients less accurate in the projection itself (the float32 torch backend
    # is off by the same amount), hence a looser gradient bound than the images'.
    for key in GAUSSIAN_INPUTS:
        assert_close(grads[key], ref_grads[key], 3e-5, f"d/d{key}")


def test_cpp_result_does_not_depend_on_thread_count():
    scene = random_scene(n=400, cameras=2, width=90, height=70, seed=13, scale_range=(0.01, 0.05))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        out_one, grads_one = render_with_grads(scene, "cpp", torch.float32)
        torch.set_num_threads(3)
        out_three, grads_three = render_with_grads(scene, "cpp", torch.float32)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(out_one, out_three, strict=True):
        assert torch.equal(a, b)
    for key in GAUSSIAN_INPUTS:
        assert torch.equal(grads_one[key], grads_three[key]), f"d/d{key} changed with the thread count"


def projection_scene(seed: int) -> dict:
    """Random Gaussians including clamped (far off to the side), culled (behind, zero scale) and unnormalised
    quaternions, in float32."""
    scene = random_scene(n=200, cameras=3, width=64, height=48, seed=seed, dtype=torch.float32)
    scene["means"][:10, 0] += 0.8  # beyond 1.3x the field of view: the Jacobian clamp
    scene["means"][10:13, 2] -= 2.0  # behind the cameras
    scene["scales"][13:15] = 0.0
    scene["quats"] = scene["quats"] * 3.0
    return scene


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_compiled_projection_matches_torch_projection(mode):
    scene = projection_scene(seed=21)
    names = ("means", "quats", "scales", "opacities")
    results = []
    for project in (project_gaussians, project_gaussians_cpp):
        leaves = {k: scene[k].clone().requires_grad_(True) for k in names}
        proj = project(**leaves, w2c=scene["w2c"], K=scene["K"], width=64, height=48, mode=mode)
        g = torch.Generator().manual_seed(5)
        outputs = (proj.means2d, proj.conics, proj.depths, proj.opacities)
        loss = sum((t * torch.rand(t.shape, generator=g)).sum() for t in outputs)
        loss.backward()
        results.append(([t.detach() for t in outputs], proj.radii, {k: v.grad for k, v in leaves.items()}))
    (ref_out, ref_radii, ref_grads), (out, radii, grads) = results
    visible = (ref_radii > 0).any(-1)
    assert 300 < int(visible.sum()) < visible.numel()
    # radii round up a float32 expression: allow a one-pixel difference on rare ties
    assert int((radii - ref_radii).abs().max()) <= 1 and float((radii != ref_radii).float().mean()) < 0.01
    for label, a, b in zip(("means2d", "conics", "depths", "opacities"), out, ref_out, strict=True):
        assert_close(a[visible], b[visible], 1e-5, label)
    for key in names:
        # the torch projection's antialiased gradient of a zero-scale Gaussian is NaN (sqrt at 0); ours is finite
        assert bool(torch.isfinite(grads[key]).all()), f"d/d{key} not finite"
        finite = torch.isfinite(ref_grads[key]).reshape(ref_grads[key].shape[0], -1).all(-1)
        assert int((~finite).sum()) <= (2 if mode == "antialiased" else 0)
        assert_close(grads[key][finite], ref_grads[key][finite], 1e-5, f"d/d{key}")


def test_cpp_backend_with_camera_gradients_matches_torch_backend():
    """Optimised cameras take the PyTorch projection; the compiled compositor still runs."""
    scene = random_scene(seed=3, dtype=torch.float32)
    grads = []
    for backend in ("torch", "cpp"):
        w2c = scene["w2c"].clone().requires_grad_(True)
        out = rasterize(**{**scene, "w2c": w2c}, backend=backend)
        (out.features.sum() + out.alpha.sum()).backward()
        grads.append(w2c.grad)
    assert float(grads[0].abs().max()) > 0
    assert_close(grads[1], grads[0], 1e-4, "d/dw2c")
