"""Real spherical harmonics of any order, light projection and Lambertian irradiance.

Convention (the one gsplat, Inria 3DGS and RGCA share): real, orthonormal SH with the Condon-Shortley phase,
polar axis +z, azimuth measured from +x towards +y, coefficient index ``i = l*l + l + m`` for
``m = -l..l``. Order ``n`` has ``(n + 1)**2`` coefficients (order 3 -> 16, order 8 -> 81).

The basis is evaluated from Cartesian coordinates (``sin^m(theta) e^{i m phi} = (x + i y)^m`` on the unit
sphere), so it is a polynomial in the direction: exact at the poles and with finite gradients everywhere.

Coefficient tensors are laid out channel-first, ``(..., C, K)``, as RGCA stores its light (``B x 3 x 81``).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F


def sh_count(order: int) -> int:
    """Number of real SH coefficients up to ``order`` (inclusive): ``(order + 1) ** 2``."""
    if order < 0:
        raise ValueError(f"SH order must be >= 0, got {order}")
    return (order + 1) ** 2


def sh_order_from_count(count: int) -> int:
    """Inverse of :func:`sh_count`; raises if ``count`` is not a perfect square."""
    order = math.isqrt(count) - 1
    if count < 1 or (order + 1) ** 2 != count:
        raise ValueError(f"{count} is not a number of SH coefficients (must be (order+1)^2)")
    return order


@lru_cache(maxsize=64)
def _normalisation(order: int) -> tuple[tuple[float, ...], ...]:
    """K(l, m) = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!) for 0 <= m <= l <= order, in float64."""
    table = []
    for degree in range(order + 1):
        row = []
        for m in range(degree + 1):
            log_ratio = math.lgamma(degree - m + 1) - math.lgamma(degree + m + 1)
            row.append(math.sqrt((2 * degree + 1) / (4 * math.pi) * math.exp(log_ratio)))
        table.append(tuple(row))
    return tuple(table)


def sh_basis(order: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real orthonormal SH basis of every degree ``l <= order`` at the given directions.

    Args:
        order: maximum degree (any non-negative integer).
        dirs: ``(..., 3)`` directions; they are normalised here.

    Returns:
        ``(..., (order + 1) ** 2)`` basis values, index ``l*l + l + m``.
    """
    if dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have a trailing dimension of 3, got shape {tuple(dirs.shape)}")
    norm_table = _normalisation(order)
    unit = F.normalize(dirs, dim=-1)
    x, y, z = unit.unbind(-1)

    # cos_m / sin_m: Re and Im of (x + i y)^m, i.e. sin^m(theta) cos(m phi) and sin^m(theta) sin(m phi).
    cos_m = [torch.ones_like(x)]
    sin_m = [torch.zeros_like(x)]
    for _ in range(order):
        cos_prev, sin_prev = cos_m[-1], sin_m[-1]
        cos_m.append(x * cos_prev - y * sin_prev)
        sin_m.append(x * sin_prev + y * cos_prev)

    # legendre[l][m]: P_l^m(z) / sin^m(theta), a polynomial in z, with the Condon-Shortley phase.
    legendre: list[list[torch.Tensor]] = [[None] * (degree + 1) for degree in range(order + 1)]  # type: ignore[list-item]
    diagonal = torch.ones_like(z)
    for m in range(order + 1):
        if m > 0:
            diagonal = diagonal * (-(2 * m - 1))
        legendre[m][m] = diagonal
        if m + 1 <= order:
            legendre[m + 1][m] = (2 * m + 1) * z * diagonal
        for degree in range(m + 2, order + 1):
            legendre[degree][m] = (
                (2 * degree - 1) * z * legendre[degree - 1][m] - (degree + m - 1) * legendre[degree - 2][m]
            ) / (degree - m)

    terms = []
    sqrt2 = math.sqrt(2.0)
    for degree in range(order + 1):
        for m in range(-degree, degree + 1):
            k = norm_table[degree][abs(m)]
            if m == 0:
                terms.append(k * legendre[degree][0])
            elif m > 0:
                terms.append((sqrt2 * k) * legendre[degree][m] * cos_m[m])
            else:
                terms.append((sqrt2 * k) * legendre[degree][-m] * sin_m[-m])
    return torch.stack(terms, dim=-1)


def eval_sh(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate an SH expansion.

    Args:
        coeffs: ``(..., C, K)`` coefficients, ``K = (order + 1) ** 2``.
        dirs: ``(..., 3)`` directions (broadcast against ``coeffs``' leading dimensions).

    Returns:
        ``(..., C)`` values ``sum_k coeffs[..., c, k] * Y_k(dirs)``.
    """
    order = sh_order_from_count(coeffs.shape[-1])
    basis = sh_basis(order, dirs)
    return (coeffs * basis.unsqueeze(-2)).sum(-1)


def project_directions_to_sh(dirs: torch.Tensor, weights: torch.Tensor, order: int) -> torch.Tensor:
    """Project weighted Dirac deltas (directional lights, quadrature samples) onto SH.

    ``L_lm = sum_n weights_n Y_lm(dirs_n)``. For a point or directional light, ``weights`` is its
    irradiance; for an environment-map quadrature it is radiance times the sample's solid angle.

    Args:
        dirs: ``(..., N, 3)`` directions the light arrives from.
        weights: ``(..., N, C)`` per-direction weights (e.g. RGB).
        order: SH order.

    Returns:
        ``(..., C, (order + 1) ** 2)``.
    """
    if weights.shape[-2] != dirs.shape[-2]:
        raise ValueError(
            f"dirs {tuple(dirs.shape)} and weights {tuple(weights.shape)} disagree on the number of directions"
        )
    basis = sh_basis(order, dirs)  # (..., N, K)
    return torch.einsum("...nc,...nk->...ck", weights, basis)


def lambert_zonal_coefficients(order: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Ramamoorthi-Hanrahan ``A_l``: the clamped-cosine kernel ``max(cos, 0)`` in SH, per degree.

    Convolving radiance ``L_lm`` with the kernel gives irradiance ``E_lm = A_l L_lm``. ``A_0 = pi``,
    ``A_1 = 2 pi / 3``, ``A_l = 0`` for odd ``l > 1`` and, for even ``l``,
    ``A_l = 2 pi (-1)^(l/2 - 1) / ((l + 2)(l - 1)) * l! / (2^l ((l/2)!)^2)``.

    Returns:
        ``(order + 1,)`` tensor.
    """
    values = []
    for degree in range(order + 1):
        if degree == 0:
            values.append(math.pi)
        elif degree == 1:
            values.append(2.0 * math.pi / 3.0)
        elif degree % 2 == 1:
            values.append(0.0)
        else:
            half = degree // 2
            log_central = math.lgamma(degree + 1) - degree * math.log(2.0) - 2.0 * math.lgamma(half + 1)
            sign = -1.0 if (half - 1) % 2 else 1.0
            values.append(2.0 * math.pi * sign / ((degree + 2) * (degree - 1)) * math.exp(log_central))
    return torch.tensor(values, dtype=dtype)


def expand_per_degree(per_degree: torch.Tensor) -> torch.Tensor:
    """Repeat a per-degree ``(..., order + 1)`` tensor to per-coefficient ``(..., (order + 1) ** 2)``."""
    order = per_degree.shape[-1] - 1
    repeats = torch.tensor([2 * degree + 1 for degree in range(order + 1)], device=per_degree.device)
    return torch.repeat_interleave(per_degree, repeats, dim=-1, output_size=(order + 1) ** 2)


def irradiance_sh(radiance_sh: torch.Tensor) -> torch.Tensor:
    """Irradiance SH from radiance SH by the clamped-cosine convolution (``E_lm = A_l L_lm``).

    Args:
        radiance_sh: ``(..., C, K)`` incident radiance.

    Returns:
        ``(..., C, K)``; ``eval_sh(result, n)`` is the irradiance on a surface with normal ``n``.
    """
    order = sh_order_from_count(radiance_sh.shape[-1])
    kernel = lambert_zonal_coefficients(order, dtype=radiance_sh.dtype).to(radiance_sh.device)
    return radiance_sh * expand_per_degree(kernel)


def lambertian_transfer(normals: torch.Tensor, order: int) -> torch.Tensor:
    """SH transfer of an unshadowed Lambertian surface: ``d_lm = A_l Y_lm(n) / pi``.

    With it, ``sum_k d_k L_k`` is ``E(n) / pi``, so ``albedo * sum_k d_k L_k`` is the Lambertian radiance.
    Useful to initialise or supervise RGCA's learned transfer.

    Args:
        normals: ``(..., 3)`` surface normals.
        order: SH order.

    Returns:
        ``(..., (order + 1) ** 2)``.
    """
    kernel = lambert_zonal_coefficients(order, dtype=normals.dtype).to(normals.device)
    return sh_basis(order, normals) * expand_per_degree(kernel) / math.pi
