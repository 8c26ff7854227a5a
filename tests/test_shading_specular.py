"""RGCA shading: SG specular (point, directional, environment), diffuse SH transfer, normals."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from relightanyone.render.envmap import envmap_to_directional_lights, latlong_directions, prefilter_envmap
from relightanyone.render.lights import fibonacci_sphere_directions
from relightanyone.render.sh import lambertian_transfer
from relightanyone.render.shading import (
    RGCA_SG_CONSTANT,
    angle_from_cos,
    assemble_transfer,
    combine_diffuse_specular,
    diffuse_color,
    point_light_sh,
    reflect,
    reflected_view_directions,
    rgca_roughness,
    sg_lobe,
    sg_lobe_integral,
    shading_normals,
    specular_directional_lights,
    specular_envmap,
    specular_point_lights,
)


def _lobes(count: int, seed: int = 0, dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    dirs = F.normalize(torch.randn(1, count, 3, generator=generator, dtype=dtype), dim=-1)
    return dirs


@pytest.mark.parametrize("sigma", [0.1, 0.3])
def test_sg_specular_of_a_light_swept_over_the_sphere_integrates_to_the_lobe_integral(sigma):
    """Sum of one unit light placed at N uniform directions, each weighted 4 pi / N, = int G dw."""
    count = 40000
    light_dirs = fibonacci_sphere_directions(count, torch.float64)[None]
    irradiance = torch.full((1, count, 1), 4.0 * math.pi / count, dtype=torch.float64)
    lobe_dirs = _lobes(3)
    sigmas = torch.full((1, 3), sigma, dtype=torch.float64)
    for normalization in ("rgca", "unit", "none"):
        total = specular_directional_lights(
            lobe_dirs, sigmas, light_dirs, irradiance, normalization=normalization
        )
        expected = sg_lobe_integral(sigmas, normalization)
        torch.testing.assert_close(total[..., 0], expected, rtol=2e-3, atol=0)
    # Small-lobe closed forms: int exp(-theta^2 / 2 s^2) dw ~ 2 pi s^2, so RGCA's lobe integrates to ~2.07 s.
    assert sg_lobe_integral(torch.tensor(0.05, dtype=torch.float64), "none").item() == pytest.approx(
        2 * math.pi * 0.05**2, rel=2e-3
    )
    assert sg_lobe_integral(torch.tensor(0.05, dtype=torch.float64)).item() == pytest.approx(
        2 * math.pi * 0.05 / RGCA_SG_CONSTANT, rel=2e-3
    )


def test_point_light_on_the_lobe_axis_gives_the_peak_and_falls_off_with_distance():
    position = torch.zeros(1, 1, 3)
    lobe = torch.tensor([[[0.0, 0.0, 1.0]]])
    sigma = torch.tensor([[0.2]])
    intensity = torch.tensor([[[4.0, 2.0, 1.0]]])
    near = specular_point_lights(position, lobe, sigma, torch.tensor([[[0.0, 0.0, 1.0]]]), intensity)
    far = specular_point_lights(position, lobe, sigma, torch.tensor([[[0.0, 0.0, 2.0]]]), intensity)
    torch.testing.assert_close(near[0, 0], intensity[0, 0] / (0.2 * RGCA_SG_CONSTANT), rtol=1e-4, atol=0)
    torch.testing.assert_close(far, near / 4.0)
    raw = specular_point_lights(
        position, lobe, sigma, torch.tensor([[[0.0, 0.0, 2.0]]]), intensity, inverse_square=False
    )
    torch.testing.assert_close(raw, near)
    # One sigma off the axis: exp(-1/2) of the peak.
    off_axis = torch.tensor([[[math.sin(0.2), 0.0, math.cos(0.2)]]])
    side = specular_point_lights(position, lobe, sigma, off_axis, intensity)
    torch.testing.assert_close(side, near * math.exp(-0.5), rtol=1e-4, atol=0)


def test_point_lights_use_the_direction_from_each_gaussian():
    positions = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    lobes = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]])
    light = torch.tensor([[[0.0, 0.0, 1.0]]])
    result = specular_point_lights(positions, lobes, torch.full((1, 2), 0.1), light, torch.ones(1, 1, 3))
    assert result[0, 0, 0] > 100 * result[0, 1, 0]  # the light is 45 degrees off the second lobe


def test_far_point_lights_match_directional_lights_and_padding_is_inert():
    lobes = _lobes(50, seed=1)
    sigma = torch.rand(1, 50, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 0.5 + 0.05
    dirs = fibonacci_sphere_directions(30, torch.float64)[None]
    irradiance = torch.rand(1, 30, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    directional = specular_directional_lights(lobes, sigma, dirs, irradiance)
    distance = 1e5
    point = specular_point_lights(
        torch.zeros(1, 50, 3, dtype=torch.float64), lobes, sigma, dirs * distance, irradiance * distance**2
    )
    torch.testing.assert_close(point, directional, rtol=1e-6, atol=1e-9)
    padded = specular_directional_lights(
        lobes,
        sigma,
        torch.cat([dirs, dirs[:, :5]], 1),
        torch.cat([irradiance, torch.zeros(1, 5, 3, dtype=torch.float64)], 1),
    )
    torch.testing.assert_close(padded, directional)
    visibility = torch.full((1, 50), 0.25, dtype=torch.float64)
    torch.testing.assert_close(
        specular_directional_lights(lobes, sigma, dirs, irradiance, visibility=visibility), directional * 0.25
    )


def test_chunking_matches_and_gradients_flow():
    torch.manual_seed(0)
    positions = torch.randn(2, 37, 3, dtype=torch.float64, requires_grad=True)
    lobes = F.normalize(torch.randn(2, 37, 3, dtype=torch.float64), dim=-1).requires_grad_(True)
    sigma = (torch.rand(2, 37, dtype=torch.float64) * 0.4 + 0.05).requires_grad_(True)
    lights = torch.randn(2, 5, 3, dtype=torch.float64) * 3
    intensity = torch.rand(2, 5, 3, dtype=torch.float64, requires_grad=True)
    outputs, grads = [], []
    for chunk in (8, 1000):
        out = specular_point_lights(positions, lobes, sigma, lights, intensity, chunk_size=chunk)
        out.square().sum().backward()
        outputs.append(out.detach())
        grads.append([t.grad.clone() for t in (positions, lobes, sigma, intensity)])
        for t in (positions, lobes, sigma, intensity):
            t.grad = None
    torch.testing.assert_close(outputs[0], outputs[1])
    for first, second in zip(grads[0], grads[1], strict=True):
        torch.testing.assert_close(first, second)
    # A light exactly on the lobe axis keeps the gradient finite.
    axis = torch.tensor([[[0.0, 0.0, 1.0]]], requires_grad=True)
    specular_point_lights(
        torch.zeros(1, 1, 3),
        axis,
        torch.tensor([[0.05]]),
        torch.tensor([[[0.0, 0.0, 2.0]]]),
        torch.ones(1, 1, 3),
    ).sum().backward()
    assert torch.isfinite(axis.grad).all()


def test_environment_specular_matches_the_environment_as_directional_lights():
    dirs = latlong_directions(64, 128, torch.float64)
    axis = F.normalize(torch.tensor([0.3, 0.5, 0.8], dtype=torch.float64), dim=0)
    env = torch.stack(
        [
            1.0 + 4.0 * torch.clamp(dirs @ axis, min=0) ** 3,
            0.5 + dirs[..., 1].clamp(min=0),
            torch.full(dirs.shape[:2], 0.3, dtype=torch.float64),
        ]
    )
    chain = prefilter_envmap(env.float(), num_levels=3, sigma_step=0.2, base_height=64)
    lobes = _lobes(40, seed=5)
    sigma = torch.full((1, 40), 0.4, dtype=torch.float64)  # exactly level 2
    lights = envmap_to_directional_lights(env, 64, 128)
    for normalization in ("unit", "rgca"):
        reference = specular_directional_lights(
            lobes, sigma, lights.directions[None], lights.irradiance[None], normalization=normalization
        )
        from_mips = specular_envmap(lobes.float(), sigma.float(), chain, normalization=normalization)
        torch.testing.assert_close(from_mips.double(), reference, rtol=0.03, atol=0)
    # White furnace: a uniform environment of radiance 1 gives specular 1 with the energy-preserving lobe.
    white = prefilter_envmap(torch.ones(3, 16, 32), num_levels=2, base_height=16)
    furnace = specular_envmap(lobes.float(), torch.full((1, 40), 0.13), white, normalization="unit")
    torch.testing.assert_close(furnace, torch.ones(1, 40, 3))
    # A yaw rotation of the lookup equals rotating the environment the other way.
    rotation = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]])
    turned = specular_envmap(lobes.float(), sigma.float(), chain, env_rotation=rotation)
    direct = specular_envmap((lobes.float() @ rotation[0].T), sigma.float(), chain)
    torch.testing.assert_close(turned, direct)


def test_reflection_and_normals():
    normal = torch.tensor([[0.0, 0.0, 1.0]])
    torch.testing.assert_close(
        reflect(torch.tensor([[1.0, 0.0, -1.0]]), normal), torch.tensor([[1.0, 0.0, 1.0]]) / math.sqrt(2)
    )
    # Camera in front of a Gaussian whose normal faces it: the lobe points back at the camera.
    lobe = reflected_view_directions(torch.zeros(1, 1, 3), torch.tensor([[0.0, 0.0, 3.0]]), normal[None])
    torch.testing.assert_close(lobe, torch.tensor([[[0.0, 0.0, 1.0]]]))
    bent = shading_normals(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
    torch.testing.assert_close(bent, torch.tensor([[1.0, 0.0, 1.0]]) / math.sqrt(2))
    assert rgca_roughness(torch.tensor([0.0, -10.0])).tolist() == pytest.approx([0.1, 0.01])
    assert sg_lobe(torch.tensor(0.0), torch.tensor(0.2), "none").item() == 1.0
    with pytest.raises(ValueError, match="unknown lobe normalization"):
        sg_lobe(torch.tensor(0.0), torch.tensor(0.2), "phong")
    # The sharpest RGCA lobe keeps its peak in float32, with a finite slope at the axis.
    cos = torch.tensor([1.0, 1.0 - 1e-6, -1.0], requires_grad=True)
    values = sg_lobe(angle_from_cos(cos), torch.tensor(0.01), "none")
    assert values[0].item() == pytest.approx(1.0, rel=2e-3)
    assert angle_from_cos(cos)[2].item() == pytest.approx(math.pi, rel=1e-3)
    values.sum().backward()
    assert torch.isfinite(cos.grad).all()
    # Just inside the axis the slope is the analytic limit lobe / sigma^2.
    assert cos.grad[1].item() == pytest.approx(values[1].item() / 0.01**2, rel=1e-2)


def test_lambertian_sphere_lit_by_a_point_light_through_the_sh_path():
    light_position = torch.tensor([[[0.0, 2.0, 2.0]]], dtype=torch.float64)  # 2.83 m from the head centre
    intensity = torch.tensor([[[8.0, 4.0, 2.0]]], dtype=torch.float64)
    light_sh = point_light_sh(light_position, intensity, order=8)
    normals = F.normalize(
        torch.randn(1, 500, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(7)), dim=-1
    )
    albedo = torch.full((1, 500, 3), 0.6, dtype=torch.float64)
    transfer = lambertian_transfer(normals, 8)[:, :, None, :]  # monochrome transfer
    radiance = diffuse_color(albedo, transfer, light_sh)
    cos = (normals @ F.normalize(light_position[0, 0], dim=0)).clamp(min=0)
    analytic = 0.6 / math.pi * intensity[0, 0] / 8.0 * cos[..., None]
    assert (radiance - analytic).abs().max() < 0.04 * 0.6 / math.pi * 8.0 / 8.0
    # RGCA's convention (no falloff) is the plain projection of the intensities.
    raw = point_light_sh(light_position, intensity, order=2, inverse_square=False)
    torch.testing.assert_close(raw, point_light_sh(light_position, intensity, order=2) * 8.0)
    centred = point_light_sh(
        light_position + 1.0, intensity, order=2, centre=torch.ones(1, 3, dtype=torch.float64)
    )
    torch.testing.assert_close(centred, point_light_sh(light_position, intensity, order=2))


def test_rgca_transfer_layout_and_colour_combination():
    color = torch.randn(2, 10, 3, 16)
    mono = torch.randn(2, 10, 1, 65)
    transfer = assemble_transfer(color, mono)
    assert transfer.shape == (2, 10, 3, 81)
    torch.testing.assert_close(transfer[:, :, 1, 16:], mono[:, :, 0])
    light = torch.randn(2, 3, 81)
    albedo = torch.rand(2, 10, 3)
    expected = albedo * torch.einsum("bnck,bck->bnc", transfer, light)
    torch.testing.assert_close(diffuse_color(albedo, transfer, light), expected)
    with pytest.raises(ValueError, match="81 SH coefficients but the light has 16"):
        diffuse_color(albedo, transfer, light[..., :16])
    combined = combine_diffuse_specular(torch.tensor([-1.0, 0.5]), torch.tensor([0.25, -1.0]))
    assert combined.tolist() == [0.25, 0.0]
