"""Stage-1 objective and the image terms every training objective shares (L1, SSIM, background composite).

L = 10·L1 + 0.2·(1 − SSIM) + 0.4·vertex L2 + 0.01·scale bound + λ_t·‖δt‖², λ_t annealed 1 → 0.001.
Image terms count masked pixels only; training composites render and target over a random background
first (:func:`composite_over_background`), so the weight covers the crop's valid pixels (all but the
padding past the source image). Vertex L2 is in mm² (RGCA's unit, for which its 0.4 weight was chosen);
δt and scales are in texel spacings (see :mod:`relightanyone.model.networks.gaussians`).
"""

from __future__ import annotations

import torch
from kornia.metrics import ssim as kornia_ssim

from relightanyone.model.metrics import SSIM_WINDOW
from relightanyone.model.networks.gaussians import MAX_SCALE, MIN_SCALE, Gaussians
from relightanyone.model.networks.presets import LossWeights

METRES_TO_MM = 1000.0


def _check_images(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> None:
    if render.shape != target.shape or render.ndim != 4:
        raise ValueError(
            f"render and target must both be (B, C, H, W); got {tuple(render.shape)}, {tuple(target.shape)}"
        )
    if mask.shape != (render.shape[0], 1, *render.shape[2:]):
        raise ValueError(
            f"mask must be (B, 1, H, W) = {(render.shape[0], 1, *render.shape[2:])}, got {tuple(mask.shape)}"
        )


def _per_sample_masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """values (B, C, H, W), mask (B, 1, H, W) -> (B,) mean of values over each sample's masked pixels."""
    weight = mask.expand_as(values)
    return (values * weight).sum(dim=(1, 2, 3)) / weight.sum(dim=(1, 2, 3)).clamp(min=1.0)


def masked_l1(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-sample mean absolute error over masked pixels and channels, (B,).

    render, target (B, C, H, W); mask (B, 1, H, W). Per-sample values keep the batch loss a plain mean
    over samples, so data-parallel gradient averaging equals one process with the whole batch.
    """
    _check_images(render, target, mask)
    return _per_sample_masked_mean((render - target).abs(), mask)


def ssim_loss(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The SSIM training term: per-sample ``1 − SSIM`` (11×11 Gaussian window, kornia), (B,).

    The SSIM map is averaged with the soft mask as weights, on unclipped images, so it stays differentiable
    everywhere; both images are masked first so the unmodelled background does not enter the windows.
    (The SSIM *metric*, :func:`relightanyone.model.metrics.masked_ssim`, clips and uses a binary mask.)
    Shapes as :func:`masked_l1`.
    """
    _check_images(render, target, mask)
    return 1.0 - _per_sample_masked_mean(kornia_ssim(render * mask, target * mask, SSIM_WINDOW), mask)


def composite_over_background(
    render: torch.Tensor,
    alpha: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    background: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Put the render and the masked target over one background colour per sample.

    render, target (B, 3, H, W); alpha, mask (B, 1, H, W) in [0, 1]; background (B, 3).
    Returns (render + (1 − alpha)·bg, target·mask + bg·(1 − mask)), both (B, 3, H, W).

    Compared over the whole crop, these make coverage part of the image: the head must be opaque
    inside its mask and empty outside. A loss over masked pixels alone lets a fog of large, faint
    Gaussians with brightened colours reproduce a flat-lit image; that fog then blurs every relit
    render, because each pixel mixes the shading of surface points centimetres apart.
    """
    # The colours are drawn on the host; they follow the render to its device and dtype.
    bg = background.to(device=render.device, dtype=render.dtype)[:, :, None, None]
    return render + (1.0 - alpha) * bg, target * mask + bg * (1.0 - mask)


def vertex_l2(
    vertices: torch.Tensor, tracked_vertices: torch.Tensor, has_mesh: torch.Tensor | None = None
) -> torch.Tensor:
    """Per-sample mean squared vertex distance in mm², (B,). vertices, tracked_vertices (B, V, 3) in metres;
    has_mesh (B,) 0/1 zeroes samples without a tracked mesh."""
    if vertices.shape != tracked_vertices.shape:
        raise ValueError(
            f"decoded mesh {tuple(vertices.shape)} and tracked mesh {tuple(tracked_vertices.shape)} differ"
        )
    per_sample = (((vertices - tracked_vertices) * METRES_TO_MM) ** 2).sum(-1).mean(-1)
    return per_sample if has_mesh is None else per_sample * has_mesh


def scale_bound_loss(scales_preclip: torch.Tensor) -> torch.Tensor:
    """RGCA-style scale regulariser on unclamped scales (texel spacings), (B, N, 3) -> (B,).

    1/s below MIN_SCALE, (s − MAX_SCALE)² above MAX_SCALE, 0 in between.
    """
    below = torch.where(
        scales_preclip < MIN_SCALE, 1.0 / scales_preclip.clamp(min=1e-6), torch.zeros_like(scales_preclip)
    )
    above = torch.where(
        scales_preclip > MAX_SCALE, (scales_preclip - MAX_SCALE) ** 2, torch.zeros_like(scales_preclip)
    )
    return (below + above).mean(dim=(1, 2))


def offset_l2(offsets: torch.Tensor) -> torch.Tensor:
    """Mean ‖δt‖² in texel spacings², offsets (B, N, 3) -> (B,)."""
    return (offsets**2).sum(-1).mean(-1)


def offset_weight(iteration: int, weights: LossWeights, anneal_iterations: int) -> float:
    """λ_t at ``iteration``: log-linear from weights.offset_start to weights.offset_end over
    ``anneal_iterations``, then constant."""
    if anneal_iterations <= 0 or iteration >= anneal_iterations:
        return weights.offset_end
    fraction = max(iteration, 0) / anneal_iterations
    return float(weights.offset_start * (weights.offset_end / weights.offset_start) ** fraction)


def weighted_sum(
    terms: dict[str, torch.Tensor], weights: dict[str, float], total: torch.Tensor | None = None
) -> torch.Tensor:
    """``total + Σ weights[name] · terms[name]``, added left to right in the order of ``weights``."""
    for name, weight in weights.items():
        term = weight * terms[name]
        total = term if total is None else total + term
    return total


def geometry_terms(
    vertices: torch.Tensor,
    tracked_vertices: torch.Tensor,
    gaussians: Gaussians,
    has_mesh: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The geometry terms of the stage-1 objective, (B,) each: ``geometry`` (vertex L2), ``scale`` (scale
    bound) and ``offset`` (‖δt‖²). Shapes as :func:`stage1_loss`."""
    return {
        "geometry": vertex_l2(vertices, tracked_vertices, has_mesh),
        "scale": scale_bound_loss(gaussians.scales_preclip),
        "offset": offset_l2(gaussians.offsets),
    }


def geometry_weights(weights: LossWeights, offset_lambda: float) -> dict[str, float]:
    """The weights of :func:`geometry_terms`: vertex L2, scale bound, then λ_t."""
    return {"geometry": weights.geometry, "scale": weights.scale, "offset": offset_lambda}


def stage1_loss(
    render: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    vertices: torch.Tensor,
    tracked_vertices: torch.Tensor,
    gaussians: Gaussians,
    weights: LossWeights,
    offset_lambda: float,
    has_mesh: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Total stage-1 loss (mean over samples) and its named terms (unweighted batch means, plus ``total``),
    as detached 0-d tensors: reading them is a host synchronisation, which a trainer does only when it logs
    (:func:`as_floats`).

    render, target (B, 3, H, W); mask (B, 1, H, W); vertices, tracked_vertices (B, V, 3); has_mesh (B,).
    """
    terms = {
        "l1": masked_l1(render, target, mask),
        "ssim": ssim_loss(render, target, mask),
        **geometry_terms(vertices, tracked_vertices, gaussians, has_mesh),
    }
    image_weights = {"l1": weights.l1, "ssim": weights.ssim}
    per_sample = weighted_sum(terms, image_weights | geometry_weights(weights, offset_lambda))
    total = per_sample.mean()
    logged = batch_means(terms)
    logged["total"] = total.detach()
    logged["offset_lambda"] = offset_lambda
    return total, logged


def batch_means(terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Detached batch means of per-sample terms, still on their device (no host synchronisation)."""
    return {name: value.detach().mean() for name, value in terms.items()}


def as_floats(logged: dict[str, torch.Tensor | float]) -> dict[str, float]:
    """Logged terms as Python floats (one host synchronisation for tensors on a GPU)."""
    return {name: float(value) for name, value in logged.items()}
