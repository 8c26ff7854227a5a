"""RGCA appearance (Saito et al. 2024, §3.1): SH diffuse transfer and spherical-Gaussian specular.

Per Gaussian ``k`` with albedo ``rho``, SH transfer ``d`` (colour or monochrome), shading normal ``n``,
roughness ``sigma`` and view-dependent visibility ``v``:

* diffuse  ``c_d = rho * sum_i L_i d_i`` with ``L`` the light's SH (:func:`point_light_sh`,
  :func:`relightanyone.render.envmap.envmap_to_sh`);
* specular ``c_s = v * sum_l E_l G(angle(r, w_l); sigma)`` with ``r`` the view direction reflected about
  ``n = normalize(n_mesh + dn)``, ``w_l`` the true direction from the Gaussian to light ``l`` and ``E_l`` its
  irradiance; under an environment map the sum becomes an integral, read from a prefiltered mip chain.
* colour ``max(max(c_d, 0) + c_s, 0)``.

Falloff (a documented choice): point lights carry radiant intensity (see ``lights.py``), so by default the
irradiance is ``I / r^2`` — measured from the head centre for the diffuse SH (all Gaussians share one light
SH, as in RGCA) and from each Gaussian for the specular. ``inverse_square=False`` treats intensities as
irradiance and ignores distance, which is exactly RGCA's behaviour.

Lobe normalisation of ``G(theta) = exp(-theta^2 / (2 sigma^2)) / Z``:
``"rgca"`` ``Z = sigma sqrt(2) pi^(2/3)`` (goliath's CUDA kernel), ``"unit"`` ``Z`` = the lobe's integral
over the sphere (energy-preserving: a white environment of radiance 1 gives specular 1), ``"none"`` ``Z = 1``.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

from relightanyone.render.envmap import PrefilteredEnvmap
from relightanyone.render.sh import project_directions_to_sh

RGCA_SG_CONSTANT = math.sqrt(2.0) * math.pi ** (2.0 / 3.0)  # 3.0335..., goliath sg.cu
LOBE_NORMALIZATIONS = ("rgca", "unit", "none")


def shading_normals(mesh_normals: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """``normalize(mesh_normals + residual)``; both ``(..., 3)``."""
    return F.normalize(mesh_normals + residual, dim=-1)


def reflect(incident: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Mirror ``incident (..., 3)`` (pointing towards the surface) about unit ``normals (..., 3)``."""
    incident = F.normalize(incident, dim=-1)
    return incident - 2.0 * (incident * normals).sum(-1, keepdim=True) * normals


def reflected_view_directions(
    positions: torch.Tensor, camera_positions: torch.Tensor, normals: torch.Tensor
) -> torch.Tensor:
    """Reflect the camera -> Gaussian direction about the shading normal (RGCA's specular lobe axis).

    Args:
        positions: ``(B, N, 3)`` Gaussian centres.
        camera_positions: ``(B, 3)`` camera centres, same space.
        normals: ``(B, N, 3)`` unit shading normals.

    Returns:
        ``(B, N, 3)`` unit lobe directions.
    """
    return reflect(positions - camera_positions[:, None, :], normals)


def assemble_transfer(color_coeffs: torch.Tensor, mono_coeffs: torch.Tensor) -> torch.Tensor:
    """RGCA transfer layout: per-channel low orders then monochrome high orders.

    Args:
        color_coeffs: ``(..., C, Kc)`` coefficients of orders ``0..n_c`` (e.g. 16 for order 3).
        mono_coeffs: ``(..., 1, Km)`` coefficients of the remaining orders, shared by every channel
            (e.g. 65 to reach order 8).

    Returns:
        ``(..., C, Kc + Km)``.
    """
    expanded = mono_coeffs.expand(*color_coeffs.shape[:-1], mono_coeffs.shape[-1])
    return torch.cat([color_coeffs, expanded], dim=-1)


def point_light_sh(
    light_positions: torch.Tensor,
    light_intensities: torch.Tensor,
    order: int,
    centre: torch.Tensor | None = None,
    inverse_square: bool = True,
) -> torch.Tensor:
    """SH of point lights seen from the head centre: ``L = sum_l E_l Y(w_l)``.

    Args:
        light_positions: ``(B, L, 3)``.
        light_intensities: ``(B, L, C)``; padding lights have zero intensity.
        order: SH order (RGCA: 8).
        centre: ``(B, 3)`` head centre; the origin when None.
        inverse_square: ``E_l = I_l / |p_l - centre|^2`` if True, else ``E_l = I_l``.

    Returns:
        ``(B, C, (order + 1) ** 2)``.
    """
    offsets = light_positions if centre is None else light_positions - centre[:, None, :]
    weights = light_intensities
    if inverse_square:
        weights = weights / (offsets * offsets).sum(-1, keepdim=True).clamp_min(1e-12)
    return project_directions_to_sh(offsets, weights, order)


def diffuse_color(albedo: torch.Tensor, transfer: torch.Tensor, light_sh: torch.Tensor) -> torch.Tensor:
    """``albedo * sum_k transfer_k * light_k``.

    Args:
        albedo: ``(B, N, C)``.
        transfer: ``(B, N, C, K)`` (or ``(B, N, 1, K)`` monochrome).
        light_sh: ``(B, C, K)``.

    Returns:
        ``(B, N, C)``.
    """
    if transfer.shape[-1] != light_sh.shape[-1]:
        raise ValueError(
            f"transfer has {transfer.shape[-1]} SH coefficients but the light has {light_sh.shape[-1]}"
        )
    return albedo * (transfer * light_sh[:, None]).sum(-1)


def rgca_roughness(raw: torch.Tensor) -> torch.Tensor:
    """RGCA's roughness activation ``max(0.1 exp(raw), 0.01)`` (lobe width in radians)."""
    return torch.clamp(0.1 * torch.exp(raw), min=0.01)


@lru_cache(maxsize=8)
def _gauss_legendre(count: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(count)


def sg_lobe_integral(sigma: torch.Tensor, normalization: str = "rgca") -> torch.Tensor:
    """Integral over the sphere of the lobe ``G`` for each ``sigma (...)`` (differentiable).

    ``2 pi int_0^pi exp(-theta^2 / (2 sigma^2)) sin(theta) dtheta / Z`` by 64-point Gauss-Legendre over
    ``[0, min(pi, 9 sigma)]`` (the tail beyond is below 1e-17).
    """
    _check_normalization(normalization)
    if normalization == "unit":
        return torch.ones_like(sigma)
    nodes, weights = _gauss_legendre(64)
    upper = torch.clamp(9.0 * sigma, max=math.pi)[..., None]
    theta = (torch.as_tensor(nodes, dtype=sigma.dtype, device=sigma.device) + 1.0) * 0.5 * upper
    integrand = torch.exp(-0.5 * (theta / sigma[..., None]) ** 2) * torch.sin(theta)
    raw = (
        2.0
        * math.pi
        * 0.5
        * upper[..., 0]
        * (integrand * torch.as_tensor(weights, dtype=sigma.dtype, device=sigma.device)).sum(-1)
    )
    if normalization == "rgca":
        return raw / (sigma * RGCA_SG_CONSTANT)
    return raw


def angle_from_cos(cos_angle: torch.Tensor) -> torch.Tensor:
    """``acos`` clamped one machine epsilon inside [-1, 1], so its gradient stays finite.

    The smallest resolved angle is ~5e-4 rad in float32, which lowers the sharpest RGCA lobe (sigma = 0.01)
    by about 0.1 % at its peak. Inside the margin the lobe's slope in the cosine approaches its analytic
    limit ``lobe / sigma^2``; at the clamped ends it is zero.
    """
    margin = torch.finfo(cos_angle.dtype).eps
    return torch.acos(cos_angle.clamp(-1.0 + margin, 1.0 - margin))


def sg_lobe(angle: torch.Tensor, sigma: torch.Tensor, normalization: str = "rgca") -> torch.Tensor:
    """Angular spherical Gaussian ``exp(-angle^2 / (2 sigma^2)) / Z`` (``angle``, ``sigma`` broadcast)."""
    _check_normalization(normalization)
    lobe = torch.exp(-0.5 * (angle / sigma) ** 2)
    if normalization == "rgca":
        return lobe / (sigma * RGCA_SG_CONSTANT)
    if normalization == "unit":
        return lobe / sg_lobe_integral(sigma, "none")
    return lobe


def specular_point_lights(
    positions: torch.Tensor,
    lobe_dirs: torch.Tensor,
    sigma: torch.Tensor,
    light_positions: torch.Tensor,
    light_intensities: torch.Tensor,
    visibility: torch.Tensor | None = None,
    inverse_square: bool = True,
    normalization: str = "rgca",
    chunk_size: int = 16384,
) -> torch.Tensor:
    """SG specular of point lights, vectorised over Gaussians x lights and chunked over Gaussians.

    ``c_s = v * sum_l E_l G(angle(r, w_l))`` with ``w_l = normalize(p_l - x)`` per Gaussian and
    ``E_l = I_l / |p_l - x|^2`` (or ``I_l`` without falloff). Chunks are recomputed in the backward pass
    (activation checkpointing), so memory stays ``O(chunk_size * L)`` also when training.

    Args:
        positions: ``(B, N, 3)`` Gaussian centres.
        lobe_dirs: ``(B, N, 3)`` unit reflected view directions.
        sigma: ``(B, N)`` lobe widths (radians).
        light_positions: ``(B, L, 3)``.
        light_intensities: ``(B, L, C)``; zero for padding lights.
        visibility: ``(B, N)`` or ``(B, N, 1)`` specular visibility, or None for 1.
        inverse_square: apply ``1 / r^2`` per Gaussian-light pair.
        normalization: lobe normalisation, see the module docstring.
        chunk_size: Gaussians per chunk.

    Returns:
        ``(B, N, C)``.
    """
    _check_normalization(normalization)

    def chunk_fn(
        chunk_positions: torch.Tensor, chunk_dirs: torch.Tensor, chunk_sigma: torch.Tensor
    ) -> torch.Tensor:
        # |p - x|^2 and r.(p - x) expanded into matrix products: no (n, L, 3) temporaries.
        light_t = light_positions.transpose(1, 2)  # (B, 3, L)
        distance_sq = (
            (light_positions * light_positions).sum(-1)[:, None, :]
            - 2.0 * torch.bmm(chunk_positions, light_t)
            + (chunk_positions * chunk_positions).sum(-1, keepdim=True)
        ).clamp_min(1e-12)
        along_lobe = torch.bmm(chunk_dirs, light_t) - (chunk_dirs * chunk_positions).sum(-1, keepdim=True)
        cos_angle = along_lobe * torch.rsqrt(distance_sq)
        weights = sg_lobe(angle_from_cos(cos_angle), chunk_sigma[..., None], normalization)
        if inverse_square:
            weights = weights / distance_sq
        return torch.bmm(weights, light_intensities)

    result = _chunked(chunk_fn, (positions, lobe_dirs, sigma), chunk_size)
    return _apply_visibility(result, visibility)


def specular_directional_lights(
    lobe_dirs: torch.Tensor,
    sigma: torch.Tensor,
    light_directions: torch.Tensor,
    light_irradiance: torch.Tensor,
    visibility: torch.Tensor | None = None,
    normalization: str = "rgca",
    chunk_size: int = 16384,
) -> torch.Tensor:
    """SG specular of lights at infinity (e.g. an environment reduced to directional lights).

    Args:
        lobe_dirs: ``(B, N, 3)``; sigma: ``(B, N)``.
        light_directions: ``(B, L, 3)`` unit directions towards the lights.
        light_irradiance: ``(B, L, C)``.
        visibility: ``(B, N)`` / ``(B, N, 1)`` or None.

    Returns:
        ``(B, N, C)``.
    """
    _check_normalization(normalization)

    def chunk_fn(chunk_dirs: torch.Tensor, chunk_sigma: torch.Tensor) -> torch.Tensor:
        cos_angle = torch.bmm(chunk_dirs, light_directions.transpose(1, 2))  # (B, n, L)
        return torch.bmm(
            sg_lobe(angle_from_cos(cos_angle), chunk_sigma[..., None], normalization), light_irradiance
        )

    result = _chunked(chunk_fn, (lobe_dirs, sigma), chunk_size)
    return _apply_visibility(result, visibility)


def specular_envmap(
    lobe_dirs: torch.Tensor,
    sigma: torch.Tensor,
    envmap: PrefilteredEnvmap,
    visibility: torch.Tensor | None = None,
    env_rotation: torch.Tensor | None = None,
    normalization: str = "rgca",
) -> torch.Tensor:
    """SG specular under an environment map via its prefiltered mip chain.

    ``c_s = v * int env(w) G(angle(r, w)) dw ~= v * lobe_integral(sigma) * prefiltered(r, sigma)``, the
    continuous counterpart of :func:`specular_directional_lights` with the same normalisation.

    Args:
        lobe_dirs: ``(B, N, 3)`` reflected view directions in head space.
        sigma: ``(B, N)``.
        envmap: :class:`relightanyone.render.envmap.PrefilteredEnvmap`.
        visibility: ``(B, N)`` / ``(B, N, 1)`` or None.
        env_rotation: ``(B, 3, 3)`` head space -> environment space (e.g. ``yaw_rotation_matrix``), or None.

    Returns:
        ``(B, N, 3)``.
    """
    _check_normalization(normalization)
    dirs = lobe_dirs if env_rotation is None else torch.einsum("bxy,bny->bnx", env_rotation, lobe_dirs)
    radiance = envmap.sample(dirs, sigma)
    result = radiance * sg_lobe_integral(sigma, normalization)[..., None]
    return _apply_visibility(result, visibility)


def combine_diffuse_specular(diffuse: torch.Tensor, specular: torch.Tensor) -> torch.Tensor:
    """RGCA's final colour ``max(max(diffuse, 0) + specular, 0)``."""
    return torch.clamp(torch.clamp(diffuse, min=0.0) + specular, min=0.0)


def _chunked(fn, tensors: tuple[torch.Tensor, ...], chunk_size: int) -> torch.Tensor:
    """Apply ``fn`` to slices of ``tensors`` along dim 1 and concatenate; checkpoint when autograd is on."""
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}")
    count = tensors[0].shape[1]
    if count == 0:
        return fn(*tensors)
    outputs = []
    for start in range(0, count, chunk_size):
        pieces = tuple(t[:, start : start + chunk_size] for t in tensors)
        if torch.is_grad_enabled() and count > chunk_size:
            outputs.append(checkpoint(fn, *pieces, use_reentrant=False))
        else:
            outputs.append(fn(*pieces))
    return torch.cat(outputs, dim=1)


def _apply_visibility(specular: torch.Tensor, visibility: torch.Tensor | None) -> torch.Tensor:
    if visibility is None:
        return specular
    if visibility.ndim == specular.ndim - 1:
        visibility = visibility[..., None]
    return specular * visibility


def _check_normalization(normalization: str) -> None:
    if normalization not in LOBE_NORMALIZATIONS:
        raise ValueError(f"unknown lobe normalization '{normalization}' (use one of {LOBE_NORMALIZATIONS})")
