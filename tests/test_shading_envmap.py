"""Environment maps: orientation, rotation, SH and directional-light conversion, prefiltering, I/O."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from relightanyone.render.envmap import (
    direction_to_latlong_uv,
    envmap_to_directional_lights,
    envmap_to_sh,
    integrate_blocks,
    latlong_directions,
    latlong_solid_angles,
    load_envmap,
    prefilter_envmap,
    resample_envmap,
    rotate_envmap_yaw,
    save_envmap,
    sg_filter_envmap,
    yaw_rotation_matrix,
)
from relightanyone.render.sh import eval_sh, irradiance_sh, project_directions_to_sh

H, W = 32, 64


def _spot_envmap(row: int, cols: list[int], value: float = 100.0) -> torch.Tensor:
    env = torch.full((3, H, W), 0.01)
    env[:, row, cols] = value
    return env


def _smooth_envmap(height: int = H, width: int = W) -> torch.Tensor:
    dirs = latlong_directions(height, width, torch.float64)
    axis = F.normalize(torch.tensor([0.4, 0.6, 0.7], dtype=torch.float64), dim=0)
    lobe = torch.clamp(dirs @ axis, min=0.0) ** 2
    return torch.stack([1.0 + 2.0 * lobe, 0.5 + lobe, 0.2 + 3.0 * lobe * dirs[..., 1].abs()], 0)


def test_orientation_convention():
    cases = {
        (0.0, 0.0, 1.0): (0.5, 0.5),  # subject's front -> centre column, equator
        (1.0, 0.0, 0.0): (0.75, 0.5),  # subject's left (+x) -> three quarters
        (-1.0, 0.0, 0.0): (0.25, 0.5),  # subject's right -> one quarter
        (0.0, 1.0, 0.0): (None, 0.0),  # up -> top row
        (0.0, -1.0, 0.0): (None, 1.0),
    }
    for direction, (u, v) in cases.items():
        uv = direction_to_latlong_uv(torch.tensor(direction))
        if u is not None:
            assert uv[0].item() == pytest.approx(u)
        assert uv[1].item() == pytest.approx(v, abs=1e-6)
    behind = direction_to_latlong_uv(torch.tensor([-1e-6, 0.0, -1.0]))[0].item()
    assert behind == pytest.approx(0.0, abs=1e-5) or behind == pytest.approx(1.0, abs=1e-5)
    dirs = latlong_directions(H, W)
    # Texel centres map back to themselves.
    uv = direction_to_latlong_uv(dirs)
    torch.testing.assert_close(uv[..., 0], ((torch.arange(W) + 0.5) / W).expand(H, W), atol=1e-5, rtol=0)
    torch.testing.assert_close(
        uv[..., 1], ((torch.arange(H) + 0.5) / H)[:, None].expand(H, W), atol=1e-5, rtol=0
    )
    assert latlong_solid_angles(H, W, torch.float64).sum().item() == pytest.approx(4.0 * math.pi)


def test_front_spot_lights_the_face_and_rotating_90_degrees_moves_it_to_the_left():
    front = _spot_envmap(H // 2 - 1, [W // 2 - 1, W // 2])
    lights = envmap_to_directional_lights(front, 10, 20)
    brightest = lights.directions[lights.irradiance[:, 0].argmax()]
    assert brightest[2] > 0.9  # +z, the subject's front
    rotated = rotate_envmap_yaw(front, math.pi / 2)
    assert rotated[0, H // 2 - 1, 3 * W // 4 - 1 : 3 * W // 4 + 1].tolist() == [100.0, 100.0]
    lights_rotated = envmap_to_directional_lights(rotated, 10, 20)
    brightest = lights_rotated.directions[lights_rotated.irradiance[:, 0].argmax()]
    assert brightest[0] > 0.9  # +x, the subject's left
    # The matrix utility agrees with the image rotation.
    torch.testing.assert_close(
        yaw_rotation_matrix(math.pi / 2) @ torch.tensor([0.0, 0.0, 1.0]),
        torch.tensor([1.0, 0.0, 0.0]),
        atol=1e-6,
        rtol=0,
    )
    # SH irradiance is brightest on the side that faces the spot, in both conventions.
    normals = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    irradiance_front = eval_sh(irradiance_sh(envmap_to_sh(front, 4)), normals)[:, 0]
    irradiance_rotated = eval_sh(irradiance_sh(envmap_to_sh(rotated, 4)), normals)[:, 0]
    assert irradiance_front.argmax().item() == 0 and irradiance_rotated.argmax().item() == 1


def test_rotation_preserves_energy_and_full_turn_is_identity():
    env = _smooth_envmap().float()
    torch.testing.assert_close(rotate_envmap_yaw(env, 2.0 * math.pi), env)
    quarter_and_a_bit = rotate_envmap_yaw(env, 0.3)
    assert quarter_and_a_bit.sum().item() == pytest.approx(env.sum().item(), rel=1e-5)
    back = rotate_envmap_yaw(rotate_envmap_yaw(env, math.pi / 4), -math.pi / 4)
    torch.testing.assert_close(back, env)


def test_sh_and_directional_light_conversions_agree():
    env = _smooth_envmap()
    sh_from_map = envmap_to_sh(env, 2)
    lights = envmap_to_directional_lights(env, 10, 20)
    sh_from_lights = project_directions_to_sh(lights.directions, lights.irradiance, 2)
    # Total power is exact; low orders agree up to the 18-degree block size.
    total = (env * latlong_solid_angles(H, W, torch.float64)).sum((1, 2))
    torch.testing.assert_close(lights.irradiance.sum(0), total)
    torch.testing.assert_close(sh_from_lights[:, 0], sh_from_map[:, 0])
    torch.testing.assert_close(
        sh_from_lights, sh_from_map, atol=0.03 * sh_from_map.abs().max().item(), rtol=0
    )
    # A constant environment of radiance 1 gives irradiance pi on every normal.
    ones = torch.ones(1, H, W, dtype=torch.float64)
    normals = F.normalize(torch.randn(20, 3, dtype=torch.float64), dim=-1)
    torch.testing.assert_close(
        eval_sh(irradiance_sh(envmap_to_sh(ones, 2)), normals)[:, 0],
        torch.full((20,), math.pi, dtype=torch.float64),
        atol=0,
        rtol=1e-3,  # texel-centre quadrature of the higher bands at 32 rows
    )


def test_block_integration_and_resampling():
    env = _smooth_envmap()
    blocks = integrate_blocks(env, 7, 11)  # not a divisor of the map size
    torch.testing.assert_close(
        blocks.sum((1, 2)), (env * latlong_solid_angles(H, W, torch.float64)).sum((1, 2))
    )
    torch.testing.assert_close(
        resample_envmap(torch.full((3, H, W), 2.5), 13, 40), torch.full((3, 13, 40), 2.5)
    )


def test_sg_filter_is_an_angular_gaussian():
    height, width, sigma = 32, 64, 0.3
    env = torch.zeros(1, height, width, dtype=torch.float64)
    env[0, height // 2, 10] = 1.0
    filtered = sg_filter_envmap(env, sigma)
    dirs = latlong_directions(height, width, torch.float64)
    angle = torch.acos((dirs[height // 2] @ dirs[height // 2, 10]).clamp(-1, 1))
    ratio = filtered[0, height // 2] / filtered[0, height // 2, 10]
    near = angle < 3 * sigma
    torch.testing.assert_close(ratio[near], torch.exp(-0.5 * (angle[near] / sigma) ** 2), atol=1e-9, rtol=0)
    constant = sg_filter_envmap(torch.full((3, 16, 32), 4.0), 0.5)
    torch.testing.assert_close(constant, torch.full((3, 16, 32), 4.0), atol=1e-5, rtol=0)


def test_prefiltered_chain_lookup():
    env = _smooth_envmap().float()
    chain = prefilter_envmap(env, num_levels=3, sigma_step=0.2, base_height=32)
    assert [tuple(level.shape) for level in chain.levels] == [(3, 32, 64), (3, 16, 32), (3, 8, 16)]
    # Level 0 at texel centres returns the map itself.
    dirs = latlong_directions(32, 64)
    torch.testing.assert_close(
        chain.sample(dirs, torch.zeros(32, 64)), env.permute(1, 2, 0), atol=1e-4, rtol=1e-4
    )
    # Between levels: linear blend of the two nearest levels; beyond the last: the last.
    probe = F.normalize(torch.tensor([[0.3, 0.2, 0.9], [-0.5, -0.6, 0.1]]), dim=-1)
    at = {s: chain.sample(probe, torch.full((2,), s)) for s in (0.2, 0.3, 0.4, 0.9)}
    torch.testing.assert_close(at[0.3], 0.5 * (at[0.2] + at[0.4]))
    torch.testing.assert_close(at[0.9], at[0.4])
    # Continuous across the lat-long seam behind the subject (u wraps from 1 to 0).
    seam = F.normalize(torch.tensor([[1e-4, 0.1, -1.0], [-1e-4, 0.1, -1.0]]), dim=-1)
    values = chain.sample(seam, torch.full((2,), 0.1))
    torch.testing.assert_close(values[0], values[1], atol=1e-3, rtol=1e-3)
    # Differentiable in direction and width.
    probe = probe.clone().requires_grad_(True)
    sigma = torch.full((2,), 0.3, requires_grad=True)
    chain.sample(probe, sigma).sum().backward()
    assert torch.isfinite(probe.grad).all() and torch.isfinite(sigma.grad).all()


# Radiance RGBE shares one 8-bit exponent per texel: error relative to the texel's largest channel.
@pytest.mark.parametrize("suffix, tolerance", [(".exr", 0.0), (".hdr", 1e-2)])
def test_envmap_file_round_trip(tmp_path, suffix, tolerance):
    env = _smooth_envmap(8, 16).float()
    path = tmp_path / f"studio{suffix}"
    save_envmap(path, env)
    loaded = load_envmap(path)
    assert loaded.shape == (3, 8, 16) and loaded.dtype == torch.float32
    largest = env.amax(0, keepdim=True)
    assert ((loaded - env).abs() <= tolerance * largest).all()


def test_envmap_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.exr"):
        load_envmap(tmp_path / "nowhere.exr")
    png = tmp_path / "sky.png"
    png.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="sky.png: unsupported environment map format"):
        load_envmap(png)
    broken = tmp_path / "broken.hdr"
    broken.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="broken.hdr: OpenCV could not decode"):
        load_envmap(broken)
    nan_map = torch.ones(3, 4, 8)
    nan_map[0, 0, 0] = float("nan")
    save_envmap(tmp_path / "nan.exr", nan_map)
    with pytest.raises(ValueError, match="nan.exr: environment map has NaN"):
        load_envmap(tmp_path / "nan.exr")
