"""CUDA backend: ``gsplat.rasterization`` (the ``cuda`` extra) with our conventions.

Conversions:

- pixel centres: ours are at integer ``K`` coordinates, gsplat's at ``+0.5``, so ``cx, cy`` gain 0.5;
- depth: gsplat's ``"RGB+ED"`` appends expected depth ``Σ wᵢzᵢ / max(α, 1e-10)`` as the last channel, the
  same definition as the CPU backends;
- Gaussians whose three scales are all zero are dropped (opacity 0), as in the CPU backends;
- layout: gsplat returns ``(..., C,H,W,X)``; we return ``(..., C,X,H,W)`` and ``packed=False`` (fast for few
  cameras). Leading batch dimensions (B independent Gaussian sets, each with its own C cameras) pass
  through: gsplat renders them in one launch.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor


@functools.lru_cache(maxsize=1)
def gsplat_cuda_available() -> bool:
    """True when CUDA is present and gsplat is installed (its CUDA code compiles on first call)."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    w2c: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor,
    mode: str,
    near: float,
    far: float,
    eps2d: float,
    tile_size: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """features (..., N,F) or (..., C,N,F), background (..., C,F) → (image (..., C,F,H,W), alpha
    (..., C,1,H,W), depth (..., C,1,H,W)); Gaussians (..., N, ·), cameras (..., C, 4, 4), (..., C, 3, 3)."""
    from gsplat import rasterization

    # Same rule as the CPU backends: Gaussians with all scales zero are not drawn (gsplat would draw a dot).
    opacities = opacities * (scales != 0).any(-1).to(opacities.dtype)
    K_gsplat = K.clone()
    K_gsplat[..., 0, 2] += 0.5
    K_gsplat[..., 1, 2] += 0.5
    colors, alphas, _meta = rasterization(
        means,
        quats,
        scales,
        opacities,
        features,
        w2c,
        K_gsplat,
        width,
        height,
        near_plane=near,
        far_plane=far,
        eps2d=eps2d,
        packed=False,
        tile_size=tile_size,
        backgrounds=background,
        render_mode="RGB+ED",
        rasterize_mode=mode,
    )
    image = colors[..., :-1].movedim(-1, -3)
    depth = colors[..., -1:].movedim(-1, -3)
    return image, alphas.movedim(-1, -3), depth
