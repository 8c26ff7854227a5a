"""Rendering stage-1 Gaussians into cameras, orbit cameras, comparison strips and image grids.

Renders go through :func:`relightanyone.render.rasterize.rasterize` (pure PyTorch / C++ on CPU, gsplat on
CUDA) with a black background: training and metrics only look at masked pixels.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relightanyone.model.networks.gaussians import Gaussians
from relightanyone.render.camera import look_at_w2c
from relightanyone.render.rasterize import rasterize, rasterize_batched


def render_gaussians(
    gaussians: Gaussians, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render sample ``b`` of ``gaussians`` into camera ``b``.

    gaussians: B samples of N Gaussians; K (B, 3, 3), w2c (B, 4, 4).
    Returns image (B, 3, H, W) linear RGB and alpha (B, 1, H, W), differentiable.
    """

    batch = gaussians.means.shape[0]
    if K.shape[0] != batch or w2c.shape[0] != batch:
        raise ValueError(f"{batch} Gaussian sets but {K.shape[0]} intrinsics and {w2c.shape[0]} poses")
    # One call for the whole batch: one launch on gsplat, sample by sample on the CPU backends.
    image, alpha, _ = rasterize_batched(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        gaussians.colours,
        w2c[:, None],
        K[:, None],
        width,
        height,
    )
    return image[:, 0], alpha[:, 0]


def render_views(
    gaussians: Gaussians,
    K: torch.Tensor,
    w2c: torch.Tensor,
    width: int,
    height: int,
    sample: int = 0,
    colours: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render Gaussian set ``sample`` of ``gaussians`` into C cameras: K (C, 3, 3), w2c (C, 4, 4).

    colours: (C, N, F) per-camera features (e.g. relit colours) in place of the set's own (N, 3) colours;
    background: (F,) or (C, F), black by default. Returns image (C, F, H, W) and alpha (C, 1, H, W).
    """

    image, alpha, _ = rasterize(
        gaussians.means[sample],
        gaussians.quats[sample],
        gaussians.scales[sample],
        gaussians.opacities[sample],
        gaussians.colours[sample] if colours is None else colours,
        w2c,
        K,
        width,
        height,
        background=background,
    )
    return image, alpha


def orbit_cameras(
    count: int, radius: float, centre: np.ndarray, K: np.ndarray, elevation_deg: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` cameras on a horizontal circle around ``centre`` (canonical +y up, +z out of the face),
    starting in front of the face. Returns K (count, 3, 3) (copies of ``K``) and w2c (count, 4, 4)."""
    elevation = math.radians(elevation_deg)
    poses = []
    for index in range(count):
        azimuth = 2 * math.pi * index / count
        offset = radius * np.array(
            [
                math.sin(azimuth) * math.cos(elevation),
                math.sin(elevation),
                math.cos(azimuth) * math.cos(elevation),
            ]
        )
        poses.append(look_at_w2c(centre + offset, centre, np.array([0.0, 1.0, 0.0])))
    return np.repeat(np.asarray(K, dtype=np.float64)[None], count, axis=0), np.stack(poses)


def comparison_strip(target: torch.Tensor, render: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Ground truth | render | error, side by side: (3, H, W) each (mask (1, H, W)) -> (3, H, 3W) linear.

    The error panel is the masked absolute difference, scaled ×4 so small errors stay visible.
    """
    error = ((render - target).abs() * mask * 4.0).mean(dim=0, keepdim=True).expand(3, -1, -1)
    return torch.cat([target * mask, render, error], dim=2)


def save_png(path, image: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB image."""
    from PIL import Image

    Image.fromarray(image).save(path)


def grid(images: list[list[np.ndarray]], gap: int = 2) -> np.ndarray:
    """Rows of equally sized (H, W, 3) uint8 images -> one (rows·H, cols·W, 3) image with white gaps."""
    height, width = images[0][0].shape[:2]
    rows, columns = len(images), max(len(row) for row in images)
    canvas = np.full((rows * (height + gap) - gap, columns * (width + gap) - gap, 3), 255, np.uint8)
    for r, row in enumerate(images):
        for c, image in enumerate(row):
            canvas[
                r * (height + gap) : r * (height + gap) + height,
                c * (width + gap) : c * (width + gap) + width,
            ] = image
    return canvas
