"""Real SH basis, projection and Lambertian irradiance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from relightanyone.render.sh import (
    eval_sh,
    irradiance_sh,
    lambert_zonal_coefficients,
    lambertian_transfer,
    project_directions_to_sh,
    sh_basis,
    sh_count,
    sh_order_from_count,
)


def _random_dirs(count: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(count, 3, generator=generator, dtype=torch.float64), dim=-1)


def _sphere_quadrature(theta_nodes: int, phi_nodes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre in cos(theta) x uniform in phi: exact for SH products up to high degree."""
    cos_theta, weights = np.polynomial.legendre.leggauss(theta_nodes)
    phi = 2.0 * math.pi * (np.arange(phi_nodes) + 0.5) / phi_nodes
    cos_grid, phi_grid = np.meshgrid(cos_theta, phi, indexing="ij")
    sin_grid = np.sqrt(1.0 - cos_grid**2)
    dirs = np.stack([sin_grid * np.cos(phi_grid), sin_grid * np.sin(phi_grid), cos_grid], -1).reshape(-1, 3)
    quad_weights = np.repeat(weights, phi_nodes) * (2.0 * math.pi / phi_nodes)
    return torch.from_numpy(dirs), torch.from_numpy(quad_weights)


def test_counts():
    assert [sh_count(n) for n in (0, 2, 3, 4, 8)] == [1, 9, 16, 25, 81]
    assert sh_order_from_count(81) == 8
    with pytest.raises(ValueError, match="not a number of SH coefficients"):
        sh_order_from_count(80)


def test_basis_equals_gsplat_up_to_order_4():
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl")
    dirs = _random_dirs(2000)
    ours = sh_basis(4, dirs)
    reference = torch_impl._eval_sh_bases_fast(25, dirs)
    assert ours.shape == (2000, 25)
    torch.testing.assert_close(ours, reference, atol=1e-12, rtol=0)
    # Lower orders are prefixes of the higher ones.
    torch.testing.assert_close(sh_basis(2, dirs), ours[:, :9])


def test_basis_known_values():
    up_z = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    values = sh_basis(2, up_z)[0]
    assert values[0] == pytest.approx(0.5 / math.sqrt(math.pi))
    assert values[2] == pytest.approx(math.sqrt(3.0 / (4.0 * math.pi)))  # l=1, m=0 along +z
    assert values[1] == pytest.approx(0.0) and values[3] == pytest.approx(0.0)
    # Condon-Shortley phase as in gsplat: Y_1^{-1} = -0.4886 y, Y_1^{1} = -0.4886 x.
    plus_x_y = sh_basis(1, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64))
    assert plus_x_y[0, 3] == pytest.approx(-0.48860251190291992)
    assert plus_x_y[1, 1] == pytest.approx(-0.48860251190291992)


@pytest.mark.parametrize("order", [4, 8])
def test_basis_orthonormal_by_quadrature(order):
    dirs, weights = _sphere_quadrature(2 * order + 2, 4 * order + 4)
    basis = sh_basis(order, dirs)
    gram = basis.T @ (basis * weights[:, None])
    torch.testing.assert_close(gram, torch.eye(sh_count(order), dtype=torch.float64), atol=1e-10, rtol=0)


def test_basis_is_smooth_at_the_poles():
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64, requires_grad=True)
    basis = sh_basis(8, dirs)
    basis.sum().backward()
    assert torch.isfinite(basis).all() and torch.isfinite(dirs.grad).all()


def test_projection_of_one_light_and_round_trip():
    light_dir = F.normalize(torch.tensor([[0.2, -0.7, 0.4]], dtype=torch.float64), dim=-1)
    rgb = torch.tensor([[2.0, 1.0, 0.5]], dtype=torch.float64)
    sh = project_directions_to_sh(light_dir, rgb, 3)
    assert sh.shape == (3, 16)
    torch.testing.assert_close(sh, rgb.T * sh_basis(3, light_dir))
    # A band-limited function projected by exact quadrature returns its own coefficients.
    coeffs = torch.randn(2, 25, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    dirs, weights = _sphere_quadrature(12, 24)
    values = eval_sh(coeffs, dirs)  # (P, 2)
    torch.testing.assert_close(project_directions_to_sh(dirs, values * weights[:, None], 4), coeffs)


def test_lambert_zonal_coefficients_match_the_clamped_cosine():
    order = 6
    kernel = lambert_zonal_coefficients(order, dtype=torch.float64)
    assert kernel[:3].tolist() == pytest.approx([math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0])
    # A_l = 2 pi int max(cos, 0) P_l(cos) dcos; odd l > 1 vanish.
    x, w = np.polynomial.legendre.leggauss(64)
    x, w = 0.5 * (x + 1.0), 0.5 * w  # nodes on [0, 1]
    for degree in range(order + 1):
        legendre = np.polynomial.legendre.Legendre.basis(degree)(x)
        assert kernel[degree].item() == pytest.approx(2.0 * math.pi * np.sum(w * x * legendre), abs=1e-12)


def test_lambertian_sphere_under_a_smooth_environment_is_exact():
    """Radiance L(w) = 1 + 0.5 w.a gives irradiance E(n) = pi + (pi/3) n.a, exactly at order 1 and above."""
    axis = F.normalize(torch.tensor([0.3, 0.8, -0.5], dtype=torch.float64), dim=0)
    dirs, weights = _sphere_quadrature(16, 32)
    radiance = (1.0 + 0.5 * dirs @ axis)[:, None]
    light_sh = project_directions_to_sh(dirs, radiance * weights[:, None], 4)
    normals = _random_dirs(500, seed=1)
    irradiance = eval_sh(irradiance_sh(light_sh), normals)[:, 0]
    torch.testing.assert_close(irradiance, math.pi + math.pi / 3.0 * (normals @ axis), atol=1e-10, rtol=0)
    # The Lambertian transfer gives the radiance albedo * E / pi.
    transfer = lambertian_transfer(normals, 4)
    radiance_out = 0.7 * (transfer * light_sh[0]).sum(-1)
    torch.testing.assert_close(radiance_out, 0.7 * irradiance / math.pi, atol=1e-10, rtol=0)


def test_lambertian_sphere_under_a_directional_light_converges():
    light = F.normalize(torch.tensor([[0.3, 0.5, 0.8]], dtype=torch.float64), dim=-1)
    normals = _random_dirs(3000, seed=2)
    analytic = (normals @ light.T)[:, 0].clamp_min(0.0)
    errors = []
    for order in (2, 4, 8):
        light_sh = project_directions_to_sh(light, torch.ones(1, 1, dtype=torch.float64), order)
        irradiance = eval_sh(irradiance_sh(light_sh), normals)[:, 0]
        errors.append((irradiance - analytic).abs().max().item())
        # Far from the terminator the truncated series is already close.
        facing = (normals @ light.T)[:, 0].abs() > 0.5
        assert (irradiance - analytic)[facing].abs().max() < 0.1
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.04  # order 8, worst case at the terminator
