"""Brute-force reference compositor: every pixel × every Gaussian, one global depth sort per camera.

No tiles and no screen-space boxes: it is the oracle the tiled backends are checked against (images and
gradients). Same per-pixel rules as the tiled paths (α cap, 1/255 skip, early stop). Memory is bounded by
processing rows of pixels in chunks, checkpointed under autograd; time is O(C·H·W·N).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from relightanyone.render.rasterize_torch import Projection, alpha_composite, gaussian_alphas

DENSE_CHUNK_ELEMENTS = 1 << 21  # pixel × Gaussian pairs per chunk


def _composite_rows(
    means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, valid: Tensor, pixels: Tensor
) -> tuple[Tensor, Tensor]:
    """means2d (L,2), conics (L,3), opacities (L,), colors (L,D), valid (L,), pixels (P,2) → ((P,D), (P,))."""
    alphas, sigma_ok = gaussian_alphas(means2d[None], conics[None], opacities[None], pixels[:, None])
    weights, transmittance = alpha_composite(alphas, sigma_ok & valid[None])
    return weights @ colors, transmittance


def composite_dense(
    projection: Projection, colors: Tensor, background: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Reference compositing of all projected Gaussians at all pixels.

    colors (C,N,D), background (C,D) → (image (C,H,W,D), alpha (C,H,W)). Culled Gaussians (radii 0) are
    left out; the others are evaluated at every pixel, sorted once by depth (stable).
    """
    C, N, D = colors.shape
    device, dtype = colors.device, colors.dtype
    ys, xs = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2)
    rows_per_chunk = max(1, DENSE_CHUNK_ELEMENTS // max(1, N * width))
    images, alphas = [], []
    for cam in range(C):
        order = torch.sort(projection.depths[cam].detach(), stable=True).indices
        valid = (projection.radii[cam] > 0).any(-1)[order]
        args = (
            projection.means2d[cam, order],
            projection.conics[cam, order],
            projection.opacities[cam, order],
            colors[cam, order],
            valid,
        )
        rows_colors, rows_transmittance = [], []
        for row in range(0, height, rows_per_chunk):
            chunk_pixels = pixels[row * width : min(height, row + rows_per_chunk) * width]
            if torch.is_grad_enabled():
                out, transmittance = checkpoint(_composite_rows, *args, chunk_pixels, use_reentrant=False)
            else:
                out, transmittance = _composite_rows(*args, chunk_pixels)
            rows_colors.append(out)
            rows_transmittance.append(transmittance)
        transmittance = torch.cat(rows_transmittance)
        image = torch.cat(rows_colors) + transmittance[:, None] * background[cam]
        images.append(image.reshape(height, width, D))
        alphas.append((1.0 - transmittance).reshape(height, width))
    return torch.stack(images), torch.stack(alphas)
