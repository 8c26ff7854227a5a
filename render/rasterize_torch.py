"""Gaussian projection, tile binning and the pure-PyTorch tile compositor.

Semantics follow gsplat 1.5.3's EWA splatting (``fully_fused_projection`` + ``rasterize_to_pixels``):

- 2D covariance ``J W Σ Wᵀ Jᵀ + eps2d·I`` with the Jacobian's ``x/z`` clamped to 1.3× the field of view;
- opacity-aware extent ``min(3.33, sqrt(2 ln(255·o)))`` for the screen-space box;
- per pixel, front to back by camera-space depth: ``α = min(0.999, o·exp(-σ))``, contributions with
  ``α < 1/255`` (or ``σ < 0``) skipped, stop before the Gaussian that would take transmittance to ``≤ 1e-4``.

Pixel convention (docs/conventions.md): the centre of pixel ``(u, v)`` is at ``(u, v)`` in pixels of ``K``.
gsplat puts pixel centres at ``(u + 0.5, v + 0.5)``; the culling and Jacobian-clamp limits below are those
of gsplat evaluated with ``cx + 0.5, cy + 0.5``, so our projection equals gsplat's shifted by half a pixel.

Everything here is batched tensor code (no Python loop over Gaussians or tiles) and works in float32 and
float64 on any device.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix
from torch import Tensor
from torch.utils.checkpoint import checkpoint

ALPHA_THRESHOLD = 1.0 / 255.0  # contributions below this are skipped (gsplat ALPHA_THRESHOLD)
ALPHA_MAX = 0.999  # α cap, keeps 1 - α away from 0
TRANSMITTANCE_MIN = 1e-4  # a pixel stops before its transmittance would reach this
EXTENT_MAX = 3.33  # screen-space box half-size in standard deviations, before the opacity-aware bound

# Elements (pixels × padded list length) per compositing chunk: a few MB per intermediate tensor keeps the
# memory traffic of eager PyTorch near the caches and the autograd memory bounded (chunks are checkpointed).
CHUNK_ELEMENTS = 1 << 19


class Projection(NamedTuple):
    """Gaussians projected into C cameras (N Gaussians each); culled ones have ``radii == 0``.

    means2d (C,N,2) pixel coordinates (our convention), conics (C,N,3) the inverse 2D covariance
    ``(a, b, c) = (Σ⁻¹₀₀, Σ⁻¹₀₁, Σ⁻¹₁₁)``, depths (C,N) camera-space z, opacities (C,N) (× the antialiasing
    compensation in ``"antialiased"`` mode), radii (C,N,2) int32 half-sizes of the screen box in pixels.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    radii: Tensor


class TileBins(NamedTuple):
    """Gaussian-tile intersections sorted by (camera, tile, depth).

    flatten_ids (P,) int64 index into the flattened (C·N) Gaussians; tile_offsets (C·T+1,) int64 start of each
    tile's list in ``flatten_ids`` (tiles numbered ``c·T + ty·tiles_x + tx``); tiles_x, tiles_y, tile_size.
    """

    flatten_ids: Tensor
    tile_offsets: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int


def _matmul3(a: Tensor, b: Tensor) -> Tensor:
    """Batched product of small matrices as broadcast multiply-sum: (..., I, J) @ (..., J, K) → (..., I, K).

    Faster than ``bmm`` for millions of 3×3/2×3 products on the CPU (no per-matrix dispatch).
    """
    return (a[..., :, :, None] * b[..., None, :, :]).sum(-2)


def _row_times_matrix(row: Tensor, matrix: Tensor) -> Tensor:
    """Row vectors times per-Gaussian matrices: row (C,N,3), matrix (N,3,3) → (C,N,3) = row @ matrix."""
    return (
        row[..., 0:1] * matrix[None, :, 0, :]
        + row[..., 1:2] * matrix[None, :, 1, :]
        + row[..., 2:3] * matrix[None, :, 2, :]
    )


def covariances_from_quats_scales(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariance ``Σ = R S Sᵀ Rᵀ``.

    quats (N,4) w x y z (normalised here), scales (N,3) linear standard deviations → (N,3,3).
    """
    rotation = quaternion_to_rotation_matrix(quats)
    rs = rotation * scales[:, None, :]
    return _matmul3(rs, rs.transpose(-1, -2))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    w2c: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    mode: str = "classic",
    eps2d: float = 0.3,
    near: float = 0.01,
    far: float = 1e10,
) -> Projection:
    """EWA projection of N Gaussians into C pinhole cameras, differentiable in every floating input.

    means (N,3), quats (N,4) wxyz, scales (N,3), opacities (N,), w2c (C,4,4), K (C,3,3) → Projection.
    """
    rotation, translation = w2c[:, :3, :3], w2c[:, :3, 3]
    means_cam = (
        means[None, :, 0:1] * rotation[:, None, :, 0]
        + means[None, :, 1:2] * rotation[:, None, :, 1]
        + means[None, :, 2:3] * rotation[:, None, :, 2]
        + translation[:, None, :]
    )  # (C,N,3)

    z = means_cam[..., 2]
    in_depth_range = (z >= near) & (z <= far)
    # Culled Gaussians still flow through the arithmetic; a safe z keeps their (masked) gradients finite.
    z_safe = torch.where(in_depth_range, z, torch.ones_like(z))
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    cx, cy = K[:, 0, 2, None] + 0.5, K[:, 1, 2, None] + 0.5  # gsplat's frame: pixel centres at +0.5
    tan_fov_x, tan_fov_y = 0.5 * width / fx, 0.5 * height / fy
    # Clamp the Jacobian's x/z, y/z to 1.3× the field of view (Gaussians far outside the image would blow up).
    x_over_z = torch.minimum(
        torch.maximum(means_cam[..., 0] / z_safe, -(cx / fx + 0.3 * tan_fov_x)),
        (width - cx) / fx + 0.3 * tan_fov_x,
    )
    y_over_z = torch.minimum(
        torch.maximum(means_cam[..., 1] / z_safe, -(cy / fy + 0.3 * tan_fov_y)),
        (height - cy) / fy + 0.3 * tan_fov_y,
    )
    # cov2d = J W Σ Wᵀ Jᵀ with Σ = (R S)(R S)ᵀ, so cov2d = A Aᵀ with A = J W R S (2×3): two rows, each a
    # broadcast multiply-add on (C,N,3) tensors (much faster on the CPU than millions of tiny bmm's).
    # Row i of J W: J has rows (fx/z, 0, -fx x/z²) and (0, fy/z, -fy y/z²).
    jw_x = (fx / z_safe)[..., None] * (
        rotation[:, None, 0, :] - x_over_z[..., None] * rotation[:, None, 2, :]
    )
    jw_y = (fy / z_safe)[..., None] * (
        rotation[:, None, 1, :] - y_over_z[..., None] * rotation[:, None, 2, :]
    )
    rotation_gauss = quaternion_to_rotation_matrix(quats)  # (N,3,3)
    a_x = _row_times_matrix(jw_x, rotation_gauss) * scales[None]  # (C,N,3)
    a_y = _row_times_matrix(jw_y, rotation_gauss) * scales[None]
    cov2d_xx, cov2d_yy, cov_xy = (a_x * a_x).sum(-1), (a_y * a_y).sum(-1), (a_x * a_y).sum(-1)
    det_unblurred = cov2d_xx * cov2d_yy - cov_xy * cov_xy
    cov_xx = cov2d_xx + eps2d
    cov_yy = cov2d_yy + eps2d
    det = cov_xx * cov_yy - cov_xy * cov_xy
    det_positive = det > 0
    det_safe = torch.where(det_positive, det, torch.ones_like(det))
    conics = torch.stack([cov_yy / det_safe, -cov_xy / det_safe, cov_xx / det_safe], dim=-1)

    means2d = torch.stack(
        [
            fx * means_cam[..., 0] / z_safe + K[:, 0, 2, None],
            fy * means_cam[..., 1] / z_safe + K[:, 1, 2, None],
        ],
        dim=-1,
    )
    opacities_cam = opacities[None, :].expand(z.shape)
    if mode == "antialiased":
        ratio = det_unblurred / det_safe
        # sqrt has an infinite slope at 0 (zero-scale Gaussians): take it only where the ratio is positive.
        positive = ratio > 0
        compensation = torch.where(
            positive, torch.sqrt(torch.where(positive, ratio, torch.ones_like(ratio))), 0.0
        )
        opacities_cam = opacities_cam * compensation
    elif mode != "classic":
        raise ValueError(f"rasterize mode must be 'classic' or 'antialiased', got {mode!r}")

    with torch.no_grad():
        opaque_enough = opacities_cam >= ALPHA_THRESHOLD
        extent = torch.sqrt(
            2.0 * torch.log(torch.clamp(opacities_cam, min=ALPHA_THRESHOLD) / ALPHA_THRESHOLD)
        )
        extent = torch.clamp(extent, max=EXTENT_MAX)
        radius_x = torch.ceil(extent * torch.sqrt(torch.clamp(cov_xx, min=0.0)))
        radius_y = torch.ceil(extent * torch.sqrt(torch.clamp(cov_yy, min=0.0)))
        centre_x, centre_y = means2d[..., 0] + 0.5, means2d[..., 1] + 0.5
        on_screen = (
            (centre_x + radius_x > 0)
            & (centre_x - radius_x < width)
            & (centre_y + radius_y > 0)
            & (centre_y - radius_y < height)
        )
        # A Gaussian with all three scales zero has no extent; gsplat would still draw it as an eps2d-sized dot.
        has_extent = (scales != 0).any(-1)[None, :]
        visible = (
            in_depth_range
            & det_positive
            & opaque_enough
            & has_extent
            & ((radius_x > 0) | (radius_y > 0))
            & on_screen
        )
        radii = torch.stack([radius_x, radius_y], dim=-1) * visible[..., None]
        radii = radii.to(torch.int32)
    return Projection(means2d, conics, z, opacities_cam, radii)


def bin_gaussians_to_tiles(
    means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = 16
) -> TileBins:
    """Every (Gaussian, tile) pair whose screen box touches the tile, sorted by camera, tile and depth.

    means2d (C,N,2), radii (C,N,2) int (0 = culled), depths (C,N) → TileBins. Ties in depth keep the
    Gaussian order (stable sort), like a radix sort on the depth bits.
    """
    C, N = depths.shape
    device = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    tiles_per_camera = tiles_x * tiles_y
    with torch.no_grad():
        centre = (means2d.detach() + 0.5) / tile_size  # gsplat frame, in tiles
        radius = radii.to(means2d.dtype) / tile_size
        tile_min = torch.floor(centre - radius)
        tile_max = torch.ceil(centre + radius)
        tile_min[..., 0].clamp_(0, tiles_x)
        tile_min[..., 1].clamp_(0, tiles_y)
        tile_max[..., 0].clamp_(0, tiles_x)
        tile_max[..., 1].clamp_(0, tiles_y)
        tile_min, tile_max = tile_min.long(), tile_max.long()
        span = (tile_max - tile_min).clamp(min=0)
        visible = (radii > 0).any(-1)
        counts = (span[..., 0] * span[..., 1] * visible).reshape(-1)  # (C·N,)

        gaussian_ids = torch.repeat_interleave(torch.arange(C * N, device=device), counts)
        first_pair = torch.cumsum(counts, 0) - counts
        local = torch.arange(gaussian_ids.numel(), device=device) - first_pair[gaussian_ids]
        span_x = span[..., 0].reshape(-1)[gaussian_ids]
        tile_x = tile_min[..., 0].reshape(-1)[gaussian_ids] + local % span_x.clamp(min=1)
        tile_y = tile_min[..., 1].reshape(-1)[gaussian_ids] + local // span_x.clamp(min=1)
        camera = gaussian_ids // N
        tile_ids = camera * tiles_per_camera + tile_y * tiles_x + tile_x

        depth_rank = torch.empty(C * N, dtype=torch.long, device=device)
        depth_rank[torch.sort(depths.detach().reshape(-1), stable=True).indices] = torch.arange(
            C * N, device=device
        )
        order = torch.sort(tile_ids * (C * N) + depth_rank[gaussian_ids]).indices
        flatten_ids = gaussian_ids[order]
        per_tile = torch.bincount(tile_ids, minlength=C * tiles_per_camera)
        tile_offsets = torch.zeros(C * tiles_per_camera + 1, dtype=torch.long, device=device)
        tile_offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(flatten_ids, tile_offsets, tiles_x, tiles_y, tile_size)


def alpha_composite(alphas: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Front-to-back weights with gsplat's skip/cap/early-stop rules, along the last axis.

    alphas (..., L) raw ``o·exp(-σ)`` (the 0.999 cap is applied here), valid (..., L) bool (entry exists and
    ``σ ≥ 0``) → (weights (..., L) = ``α_i T_i``, final transmittance (...)). The stop decision is discrete
    (no gradient), as in the CUDA kernels.
    """
    if alphas.shape[-1] == 0:
        return alphas, torch.ones(alphas.shape[:-1], dtype=alphas.dtype, device=alphas.device)
    alphas = torch.clamp(alphas, max=ALPHA_MAX)
    alphas = torch.where(valid & (alphas >= ALPHA_THRESHOLD), alphas, torch.zeros_like(alphas))
    with torch.no_grad():
        keep = torch.cumprod(1.0 - alphas, dim=-1) > TRANSMITTANCE_MIN
    alphas = torch.where(keep, alphas, torch.zeros_like(alphas))
    transmittance_after = torch.cumprod(1.0 - alphas, dim=-1)
    transmittance_before = torch.cat(
        [torch.ones_like(alphas[..., :1]), transmittance_after[..., :-1]], dim=-1
    )
    return alphas * transmittance_before, transmittance_after[..., -1]


def gaussian_alphas(
    means2d: Tensor, conics: Tensor, opacities: Tensor, pixels: Tensor
) -> tuple[Tensor, Tensor]:
    """Raw ``o·exp(-σ)`` of Gaussians at pixels, with ``σ ≥ 0`` as validity.

    means2d (..., 1, L, 2), conics (..., 1, L, 3), opacities (..., 1, L), pixels (..., P, 1, 2)
    → (alphas (..., P, L), sigma_ok (..., P, L)).
    """
    delta = means2d - pixels
    dx, dy = delta[..., 0], delta[..., 1]
    sigma = 0.5 * (conics[..., 0] * dx * dx + conics[..., 2] * dy * dy) + conics[..., 1] * dx * dy
    return opacities * torch.exp(-sigma), sigma >= 0


def _composite_chunk(
    means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, valid: Tensor, pixels: Tensor
) -> tuple[Tensor, Tensor]:
    """Composite n padded tile lists of length L at their pixels.

    means2d (n,L,2), conics (n,L,3), opacities (n,L), colors (n,L,D), valid (n,L) bool, pixels (n,P,2)
    (pixels of partial tiles beyond the image are composited too and cropped later)
    → (colors (n,P,D), transmittance (n,P)).
    """
    alphas, sigma_ok = gaussian_alphas(
        means2d[:, None], conics[:, None], opacities[:, None], pixels[:, :, None]
    )
    weights, transmittance = alpha_composite(alphas, sigma_ok & valid[:, None, :])
    return weights @ colors, transmittance


def composite_tiles_torch(
    projection: Projection, colors: Tensor, background: Tensor, bins: TileBins, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Composite every tile with batched tensor operations; autograd gives the exact backward.

    Tiles are sorted by list length and padded per group of similar length (no cap on list length); each
    group is split into chunks of at most ``CHUNK_ELEMENTS`` pixel-Gaussian pairs, checkpointed under autograd
    so memory stays bounded. colors (C,N,D), background (C,D) → (image (C,H,W,D), alpha (C,H,W)).
    """
    C, N, D = colors.shape
    ts, tiles_x, tiles_y = bins.tile_size, bins.tiles_x, bins.tiles_y
    tiles_total = C * tiles_x * tiles_y
    device, dtype = colors.device, colors.dtype
    means_flat = projection.means2d.reshape(C * N, 2)
    conics_flat = projection.conics.reshape(C * N, 3)
    opacities_flat = projection.opacities.reshape(C * N)
    colors_flat = colors.reshape(C * N, D)

    local = torch.arange(ts * ts, device=device)
    local_xy = torch.stack([local % ts, local // ts], dim=-1).to(dtype)  # (P,2) within a tile
    counts = bins.tile_offsets[1:] - bins.tile_offsets[:-1]
    occupied = torch.nonzero(counts > 0).squeeze(1)
    order = torch.argsort(counts[occupied], stable=True)
    occupied = occupied[order]
    # Pad each tile's list to the next length on a ~19 % geometric grid: little padding, few distinct shapes.
    padded = torch.ceil(1.19 ** torch.ceil(torch.log(counts[occupied].to(torch.float64)) / math.log(1.19)))
    padded = torch.maximum(padded.long(), counts[occupied])

    tile_pixels: list[Tensor] = []
    tile_transmittance: list[Tensor] = []
    chunk_tiles: list[Tensor] = []
    lengths, group_sizes = torch.unique_consecutive(padded, return_counts=True)
    boundaries = torch.cumsum(group_sizes, 0)
    starts = boundaries - group_sizes
    for length, group_start, group_end in zip(
        lengths.tolist(), starts.tolist(), boundaries.tolist(), strict=True
    ):
        tiles_per_chunk = max(1, CHUNK_ELEMENTS // (ts * ts * length))
        for chunk_start in range(group_start, group_end, tiles_per_chunk):
            tiles = occupied[chunk_start : min(chunk_start + tiles_per_chunk, group_end)]
            slot = torch.arange(length, device=device)
            valid = slot[None, :] < counts[tiles, None]
            isect = torch.clamp(
                bins.tile_offsets[tiles, None] + slot, max=max(bins.flatten_ids.numel() - 1, 0)
            )
            ids = bins.flatten_ids[isect]
            camera_tile = tiles % (tiles_x * tiles_y)
            origin = torch.stack([camera_tile % tiles_x, camera_tile // tiles_x], dim=-1).to(dtype) * ts
            pixels = origin[:, None, :] + local_xy[None]
            args = (means_flat[ids], conics_flat[ids], opacities_flat[ids], colors_flat[ids], valid, pixels)
            if torch.is_grad_enabled():
                out, transmittance = checkpoint(_composite_chunk, *args, use_reentrant=False)
            else:
                out, transmittance = _composite_chunk(*args)
            tile_pixels.append(out)
            tile_transmittance.append(transmittance)
            chunk_tiles.append(tiles)

    background_tiles = background[:, None, :].expand(C, tiles_x * tiles_y, D).reshape(tiles_total, D)
    pixels_colors = background_tiles[:, None, :].expand(tiles_total, ts * ts, D)
    transmittance_all = torch.ones(tiles_total, ts * ts, device=device, dtype=dtype)
    if chunk_tiles:
        tiles_cat = torch.cat(chunk_tiles)
        bg_per_tile = background[tiles_cat // (tiles_x * tiles_y)]
        trans_cat = torch.cat(tile_transmittance)
        colored = torch.cat(tile_pixels) + trans_cat[..., None] * bg_per_tile[:, None, :]
        pixels_colors = pixels_colors.index_copy(0, tiles_cat, colored)
        transmittance_all = transmittance_all.index_copy(0, tiles_cat, trans_cat)
    elif colors.requires_grad or projection.means2d.requires_grad:
        # Nothing visible: keep the result attached to the inputs so that backward gives zero gradients.
        attached = 0.0 * (colors_flat.sum() + means_flat.sum() + conics_flat.sum() + opacities_flat.sum())
        pixels_colors = pixels_colors + attached
    image = _tiles_to_image(pixels_colors, C, tiles_y, tiles_x, ts, D)[:, :height, :width]
    transmittance_image = _tiles_to_image(transmittance_all[..., None], C, tiles_y, tiles_x, ts, 1)
    return image, 1.0 - transmittance_image[:, :height, :width, 0]


def _tiles_to_image(tiles: Tensor, C: int, tiles_y: int, tiles_x: int, ts: int, D: int) -> Tensor:
    """(C·ty·tx, ts·ts, D) tile-major pixels → (C, ty·ts, tx·ts, D) image."""
    return (
        tiles.reshape(C, tiles_y, tiles_x, ts, ts, D)
        .permute(0, 1, 3, 2, 4, 5)
        .reshape(C, tiles_y * ts, tiles_x * ts, D)
    )
