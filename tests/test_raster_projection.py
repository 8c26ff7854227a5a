"""Projection against gsplat's pure-PyTorch ``_fully_fused_projection`` (CPU), and tile binning."""

from __future__ import annotations

import pytest
import torch
from helpers.raster_scenes import project_scene, random_scene

from relightanyone.render.rasterize_torch import bin_gaussians_to_tiles, covariances_from_quats_scales

torch_impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat (dev extra) is not installed")


def shifted_K(K):
    """Our K (pixel centre at integer coordinates) → gsplat's (pixel centre at +0.5)."""
    K = K.clone()
    K[:, 0, 2] += 0.5
    K[:, 1, 2] += 0.5
    return K


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_projection_equals_gsplat_torch_reference(mode):
    scene = random_scene(n=200, cameras=3, width=64, height=48, seed=2)
    # push a few Gaussians far to the side so that the Jacobian clamp is exercised
    scene["means"][:10, 0] += 0.8
    ours = project_scene(scene, mode=mode)
    covars, _ = torch_impl._quat_scale_to_covar_preci(scene["quats"], scene["scales"], compute_preci=False)
    radii, means2d, depths, conics, compensations = torch_impl._fully_fused_projection(
        scene["means"],
        covars,
        scene["w2c"],
        shifted_K(scene["K"]),
        64,
        48,
        eps2d=0.3,
        calc_compensations=(mode == "antialiased"),
    )
    visible = (ours.radii > 0).any(-1)
    assert int(visible.sum()) > 300
    assert bool(((radii > 0).any(-1) | ~visible).all()), "we keep a Gaussian that gsplat culls"
    torch.testing.assert_close(ours.means2d[visible] + 0.5, means2d[visible], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(ours.conics[visible], conics[visible], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(ours.depths, depths)
    if mode == "antialiased":
        expected = scene["opacities"][None].expand_as(compensations) * compensations
        torch.testing.assert_close(ours.opacities[visible], expected[visible], rtol=1e-9, atol=1e-12)
    # our box is the opacity-aware one: never larger than gsplat's 3.33-sigma box
    assert bool((ours.radii[visible] <= radii[visible]).all())


def test_covariance_matches_gsplat():
    scene = random_scene(n=50, seed=4)
    covars, _ = torch_impl._quat_scale_to_covar_preci(scene["quats"], scene["scales"], compute_preci=False)
    torch.testing.assert_close(covariances_from_quats_scales(scene["quats"], scene["scales"]), covars)


def test_binning_lists_every_touched_tile_sorted_by_depth():
    scene = random_scene(n=60, cameras=2, width=70, height=50, seed=9)
    proj = project_scene(scene)
    bins = bin_gaussians_to_tiles(proj.means2d, proj.radii, proj.depths, 70, 50, tile_size=16)
    tiles_per_camera = bins.tiles_x * bins.tiles_y
    flat_depths = proj.depths.reshape(-1)
    pairs = set()
    for tile in range(bins.tile_offsets.numel() - 1):
        ids = bins.flatten_ids[bins.tile_offsets[tile] : bins.tile_offsets[tile + 1]]
        assert bool((ids // 60 == tile // tiles_per_camera).all()), "a tile lists another camera's Gaussian"
        assert bool((flat_depths[ids].diff() >= 0).all()), "tile list not sorted front to back"
        pairs.update((int(i), tile) for i in ids)
    # brute force: every visible Gaussian's box against every tile rectangle (gsplat frame, +0.5)
    expected = set()
    for flat in range(proj.depths.numel()):
        c, n = divmod(flat, 60)
        rx, ry = (int(v) for v in proj.radii[c, n])
        if rx == 0 and ry == 0:
            continue
        x, y = (float(v) + 0.5 for v in proj.means2d[c, n])
        for ty in range(bins.tiles_y):
            for tx in range(bins.tiles_x):
                if (
                    x + rx > tx * 16
                    and x - rx < (tx + 1) * 16
                    and y + ry > ty * 16
                    and y - ry < (ty + 1) * 16
                ):
                    expected.add((flat, c * tiles_per_camera + ty * bins.tiles_x + tx))
    assert pairs == expected
