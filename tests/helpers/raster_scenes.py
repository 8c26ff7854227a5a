"""Small random Gaussian scenes shared by the rasterizer tests, and how they compare backends."""

from __future__ import annotations

import torch

from relightanyone.render.rasterize import rasterize
from relightanyone.render.rasterize_torch import Projection, project_gaussians

GAUSSIAN_INPUTS = ("means", "quats", "scales", "opacities", "features")


def random_scene(
    n: int = 40,
    cameras: int = 2,
    width: int = 37,
    height: int = 29,
    channels: int = 3,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    opacity_range: tuple[float, float] = (0.05, 0.9),
    scale_range: tuple[float, float] = (0.01, 0.06),
    per_camera_features: bool = False,
) -> dict:
    """Gaussians around the origin seen by ``cameras`` pinhole cameras 1 m away → ``rasterize`` keyword args.

    Values are rounded to float32 so that float32 and float64 backends see the same scene.
    """
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    means = (rand(n, 3) - 0.5) * 0.3
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = scale_range[0] + rand(n, 3) * (scale_range[1] - scale_range[0])
    opacities = opacity_range[0] + rand(n) * (opacity_range[1] - opacity_range[0])
    features = rand(cameras, n, channels) if per_camera_features else rand(n, channels)
    w2c = torch.eye(4, dtype=torch.float64).repeat(cameras, 1, 1)
    for c in range(cameras):
        angle = 0.3 * c
        w2c[c, 0, 0], w2c[c, 0, 2], w2c[c, 2, 0], w2c[c, 2, 2] = (
            torch.cos(torch.tensor(angle)),
            torch.sin(torch.tensor(angle)),
            -torch.sin(torch.tensor(angle)),
            torch.cos(torch.tensor(angle)),
        )
        w2c[c, :3, 3] = torch.tensor([0.01 * c, -0.02 * c, 1.0])
    focal = 1.1 * width
    K = torch.tensor(
        [[focal, 0.0, (width - 1) / 2 + 0.3], [0.0, focal * 1.05, (height - 1) / 2 - 0.2], [0, 0, 1]],
        dtype=torch.float64,
    ).repeat(cameras, 1, 1)
    scene = dict(
        means=means, quats=quats, scales=scales, opacities=opacities, features=features, w2c=w2c, K=K
    )
    scene = {k: v.float().to(dtype) for k, v in scene.items()}
    return {**scene, "width": width, "height": height}


def render_with_grads(scene: dict, backend: str, dtype: torch.dtype, seed: int = 1, **kwargs):
    """Render, back-propagate a fixed random loss on all three outputs → (outputs, grads by input name)."""
    leaves = {k: scene[k].to(dtype).clone().requires_grad_(True) for k in GAUSSIAN_INPUTS}
    cams = {k: scene[k].to(dtype) for k in ("w2c", "K")}
    out = rasterize(**leaves, **cams, width=scene["width"], height=scene["height"], backend=backend, **kwargs)
    g = torch.Generator().manual_seed(seed)
    weights = [torch.rand(t.shape, generator=g, dtype=torch.float64).to(t.device, dtype) for t in out]
    loss = sum((t * w).sum() for t, w in zip(out, weights, strict=True))
    loss.backward()
    return [t.detach().double() for t in out], {k: v.grad.double() for k, v in leaves.items()}


def project_scene(scene: dict, **kwargs) -> Projection:
    """``project_gaussians`` of a :func:`random_scene` at its own image size; ``kwargs`` as there (mode)."""
    return project_gaussians(
        *(scene[k] for k in ("means", "quats", "scales", "opacities", "w2c", "K")),
        scene["width"],
        scene["height"],
        **kwargs,
    )


def assert_close(actual, expected, tol, what):
    """|actual - expected| ≤ tol · max(1, max |expected|) (a tolerance relative to the tensor's scale)."""
    scale = max(1.0, float(expected.abs().max())) if expected.numel() else 1.0
    err = float((actual - expected).abs().max()) if expected.numel() else 0.0
    assert err <= tol * scale, f"{what}: max error {err:.3g} > {tol:g} × {scale:.3g}"
