"""Relightable Gaussian appearance: decoder outputs to RGCA parameters, relit colours, stage-2 regularisers.

Both the stage-2 UNet and the single-stage baseline predict two UV maps per sample:

* view-independent, ``3 + 3K + 1`` channels: albedo ρ (3), diffuse SH transfer d (3 × K, K = (n+1)², RGB
  for every coefficient), roughness σ (1);
* view-dependent, 4 channels: specular visibility v (1), normal residual δn (3).

Activations follow RGCA (``docs/shading.md``): ``ρ = softplus``, ``σ = max(0.1 e^x, 0.01)``,
``v = sigmoid``, ``n = normalize(n̂ + δn)``. The transfer is predicted as a residual over the unshadowed
Lambertian transfer of the mesh normal n̂ (``render.sh.lambertian_transfer``), so an untrained decoder
already shades like a diffuse surface; the residual learns shadowing and interreflection.

Relit colour per Gaussian (RGCA §3.1, ``render.shading``): ``max(max(ρ Σ_k d_k L_k, 0) + c_spec, 0)``,
with ``L`` the SH of the point lights seen from the head centre and ``c_spec`` the spherical-Gaussian
specular of every light. Both terms are linear in the lights; the only non-linearity is the clamp of
negative diffuse, which the negative-diffuse regulariser keeps inactive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from relightanyone.errors import InputError
from relightanyone.render.lights import PointLights
from relightanyone.render.sh import lambertian_transfer, sh_count
from relightanyone.render.shading import (
    combine_diffuse_specular,
    diffuse_color,
    point_light_sh,
    reflected_view_directions,
    rgca_roughness,
    shading_normals,
    specular_point_lights,
)

VIEW_DEPENDENT_CHANNELS = 4  # visibility, normal residual
INITIAL_ALBEDO = 0.5
INITIAL_VISIBILITY = 0.1  # start mostly diffuse: an untrained lobe would otherwise add bright noise
FULL_ON_PATTERN = "full"
OLAT_PREFIX = "olat-"


def view_independent_channels(sh_order: int) -> int:
    """Channels of the view-independent map: albedo (3) + RGB transfer (3 (n+1)²) + roughness (1)."""
    return 3 + 3 * sh_count(sh_order) + 1


def view_independent_output_bias(sh_order: int) -> torch.Tensor:
    """(3 + 3K + 1,) initial raw value: INITIAL_ALBEDO, zero transfer residual, roughness 0.1 rad."""
    bias = torch.zeros(view_independent_channels(sh_order))
    bias[:3] = math.log(math.expm1(INITIAL_ALBEDO))  # softplus⁻¹
    return bias


def view_dependent_output_bias() -> torch.Tensor:
    """(4,) initial raw value: visibility INITIAL_VISIBILITY, no normal residual."""
    bias = torch.zeros(VIEW_DEPENDENT_CHANNELS)
    bias[0] = math.log(INITIAL_VISIBILITY / (1.0 - INITIAL_VISIBILITY))
    return bias


@dataclass
class RelightParams:
    """Per-Gaussian reflectance of a batch.

    albedo (B, N, 3) ≥ 0; transfer (B, N, 3, K); roughness (B, N) radians; visibility (B, N) in (0, 1);
    normal_residual (B, N, 3) δn; normals (B, N, 3) unit shading normals ``normalize(n̂ + δn)``.
    """

    albedo: torch.Tensor
    transfer: torch.Tensor
    roughness: torch.Tensor
    visibility: torch.Tensor
    normal_residual: torch.Tensor
    normals: torch.Tensor

    @property
    def sh_order(self) -> int:
        return int(round(math.sqrt(self.transfer.shape[-1]))) - 1


def activate_relight_params(
    view_independent: torch.Tensor,
    view_dependent: torch.Tensor,
    mesh_normals: torch.Tensor,
    sh_order: int,
    albedo_scale: torch.Tensor | None = None,
) -> RelightParams:
    """Raw per-Gaussian decoder outputs to :class:`RelightParams`.

    Args:
        view_independent: (B, N, 3 + 3K + 1) raw albedo, transfer residual, roughness.
        view_dependent: (B, N, 4) raw visibility and normal residual.
        mesh_normals: (B, N, 3) unit normals n̂ of the mesh at each Gaussian.
        sh_order: n, with K = (n + 1)².
        albedo_scale: (3,) the radiometric unit of the albedo (image units per rig-light unit), so the raw
            output stays near 1 whatever the dataset's light calibration is, or (B, N, 3) a per-Gaussian
            base the raw output multiplies (stage 2: the input texture in albedo units); ones when None.
    """
    count = sh_count(sh_order)
    expected = view_independent_channels(sh_order)
    if view_independent.shape[-1] != expected or view_dependent.shape[-1] != VIEW_DEPENDENT_CHANNELS:
        raise ValueError(
            f"expected {expected} view-independent and {VIEW_DEPENDENT_CHANNELS} view-dependent channels for SH "
            f"order {sh_order}, got {view_independent.shape[-1]} and {view_dependent.shape[-1]}"
        )
    batch, gaussians = view_independent.shape[:2]
    residual = view_independent[..., 3 : 3 + 3 * count].reshape(batch, gaussians, 3, count)
    prior = lambertian_transfer(mesh_normals, sh_order)[:, :, None, :]
    normal_residual = view_dependent[..., 1:4]
    return RelightParams(
        albedo=F.softplus(view_independent[..., 0:3]) * (1.0 if albedo_scale is None else albedo_scale),
        transfer=prior + residual,
        roughness=rgca_roughness(view_independent[..., -1]),
        visibility=torch.sigmoid(view_dependent[..., 0]),
        normal_residual=normal_residual,
        normals=shading_normals(mesh_normals, normal_residual),
    )


@dataclass
class RelitColours:
    """colour (B, N, 3) final RGCA colour; diffuse (B, N, 3) before its clamp; specular (B, N, 3)."""

    colour: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor


def relight(
    params: RelightParams,
    positions: torch.Tensor,
    camera_positions: torch.Tensor,
    light_positions: torch.Tensor,
    light_intensities: torch.Tensor,
    head_centre: torch.Tensor,
    normalization: str = "rgca",
    inverse_square: bool = True,
) -> RelitColours:
    """Colour of every Gaussian seen from a camera under point lights.

    Args:
        params: reflectance, B samples of N Gaussians.
        positions: (B, N, 3) Gaussian centres (canonical metres).
        camera_positions: (B, 3) camera centres.
        light_positions: (B, L, 3); light_intensities: (B, L, 3) radiant intensity, zero for padding.
        head_centre: (3,) or (B, 3) origin of the diffuse light SH (all Gaussians share one light SH).
        normalization, inverse_square: see :mod:`relightanyone.render.shading`.
    """
    batch = positions.shape[0]
    centre = head_centre.expand(batch, 3) if head_centre.ndim == 1 else head_centre
    light_sh = point_light_sh(light_positions, light_intensities, params.sh_order, centre, inverse_square)
    diffuse = diffuse_color(params.albedo, params.transfer, light_sh)
    lobes = reflected_view_directions(positions, camera_positions, params.normals)
    specular = specular_point_lights(
        positions,
        lobes,
        params.roughness,
        light_positions,
        light_intensities,
        params.visibility,
        inverse_square=inverse_square,
        normalization=normalization,
    )
    return RelitColours(
        colour=combine_diffuse_specular(diffuse, specular), diffuse=diffuse, specular=specular
    )


def camera_centres(w2c: torch.Tensor) -> torch.Tensor:
    """Camera positions ``-Rᵀ t`` of world-to-camera matrices: (B, 4, 4) -> (B, 3)."""
    rotation, translation = w2c[:, :3, :3], w2c[:, :3, 3]
    return -(rotation.transpose(1, 2) @ translation[..., None])[..., 0]


def pattern_light_indices(
    pattern: str, light_patterns: dict[str, int], light_count: int, source: str
) -> list[int]:
    """Rig lights that are on in an image pattern.

    ``full`` is every light; ``olat-KKK`` is the light whose ``lights.arrow`` row names that pattern (or,
    when the table names none, light KKK of the rig). ``source`` names the dataset in errors.
    """
    if pattern == FULL_ON_PATTERN:
        return list(range(light_count))
    if pattern in light_patterns:
        return [light_patterns[pattern]]
    if pattern.startswith(OLAT_PREFIX) and pattern[len(OLAT_PREFIX) :].isdigit():
        index = int(pattern[len(OLAT_PREFIX) :])
        if index < light_count and not light_patterns:
            return [index]
    raise InputError(
        f"{source}: image pattern {pattern!r} matches no rig light in lights.arrow ({light_count} lights); "
        "stage 2 trains on 'full' and 'olat-KKK' frames of an OLAT dataset"
    )


def batch_lights(rig: PointLights, indices: list[list[int]]) -> tuple[torch.Tensor, torch.Tensor]:
    """Lights of each sample, zero-padded to the longest: positions, intensities (B, Lmax, 3)."""
    longest = max(len(on) for on in indices)
    positions = rig.positions.new_zeros(len(indices), longest, 3)
    intensities = rig.intensities.new_zeros(len(indices), longest, 3)
    for sample, on in enumerate(indices):
        chosen = rig.select(on)
        positions[sample, : len(on)] = chosen.positions
        intensities[sample, : len(on)] = chosen.intensities
    return positions, intensities


# Stage-2 regularisers: each returns one value per sample, (B,), so the batch loss is a plain mean.


def negative_diffuse_loss(diffuse: torch.Tensor) -> torch.Tensor:
    """λ_c− term: mean of ``min(c_diffuse, 0)²``; diffuse (B, N, 3) -> (B,). Zero when no diffuse is negative."""
    return (diffuse.clamp(max=0.0) ** 2).mean(dim=(1, 2))


def monochrome_transfer_loss(transfer: torch.Tensor) -> torch.Tensor:
    """λ_mono term: mean squared deviation of each colour channel's transfer from the channel mean.

    transfer (B, N, C, K) -> (B,). Zero exactly when R, G and B share one transfer (a grey shadowing).
    """
    return ((transfer - transfer.mean(dim=2, keepdim=True)) ** 2).mean(dim=(1, 2, 3))


def normal_residual_loss(normal_residual: torch.Tensor) -> torch.Tensor:
    """λ_n term: mean ‖δn‖²; (B, N, 3) -> (B,)."""
    return (normal_residual**2).sum(-1).mean(-1)


def albedo_prior_loss(
    albedo: torch.Tensor, prior: torch.Tensor, unit: torch.Tensor | None = None
) -> torch.Tensor:
    """λ_ρ term: mean squared distance of the albedo from its prior, both in ``unit`` (3,) when given.

    albedo (B, N, 3), prior (N, 3) or (B, N, 3) -> (B,). Measuring in the albedo's unit keeps the term's size independent
    of the dataset's light calibration.
    """
    if unit is not None:
        albedo, prior = albedo / unit, prior / unit
    return ((albedo - prior) ** 2).mean(dim=(1, 2))


def annealed_weight(iteration: int, start: float, end: float, iterations: int) -> float:
    """A weight going from ``start`` to ``end`` over ``iterations``, then constant.

    Log-linear when both ends are positive (λ_ρ: 10 → 0.01 spans three decades), linear otherwise
    (λ_n: 1 → 0, RGCA's monotonic schedule).
    """
    if iterations <= 0 or iteration >= iterations:
        return float(end)
    fraction = max(iteration, 0) / iterations
    if start > 0 and end > 0:
        return float(start * (end / start) ** fraction)
    return float(start + (end - start) * fraction)
