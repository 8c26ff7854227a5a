"""The differentiable 3D Gaussian rasterizer: one function, several backends.

``rasterize`` splats N Gaussians into C pinhole cameras with gsplat 1.5.3's EWA semantics and returns
feature images, alpha and expected depth, differentiable with respect to every floating input.

Backends (``backend=``):

- ``"gsplat"``: ``gsplat.rasterization`` on CUDA (the ``cuda`` extra);
- ``"cpp"``: compiled C++/OpenMP projection, tile binning and compositor (CPU, float32; the PyTorch
  projection when the cameras need gradients);
- ``"torch"``: PyTorch projection, binning and batched tile compositing (any device and dtype);
- ``"dense"``: the brute-force reference, every pixel × every Gaussian (tests, small scenes);
- ``"auto"``: gsplat for CUDA tensors when installed, else cpp for float32 CPU tensors when the kernel
  builds, else torch.

``rasterize_batched`` renders B independent Gaussian sets, each into its own C cameras, in one call: gsplat
takes the batch dimension natively (one launch for all B·C images); the CPU backends render set by set.

Input values (NaN, infinite, negative scales) are checked on CPU tensors and, on a GPU, only when
:func:`set_value_checks` turned the checks on: each check reads a value back to the host, which would stall
a GPU training step on every call. Shapes and dtypes are always checked.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from relightanyone.render import rasterize_cpp
from relightanyone.render.rasterize_cpp import tile_kernel_available
from relightanyone.render.rasterize_dense import composite_dense
from relightanyone.render.rasterize_gsplat import gsplat_cuda_available, rasterize_gsplat
from relightanyone.render.rasterize_torch import (
    bin_gaussians_to_tiles,
    composite_tiles_torch,
    project_gaussians,
)

BACKENDS = ("auto", "cpp", "torch", "dense", "gsplat")
MODES = ("classic", "antialiased")
_VALUE_CHECKS_ON_GPU = [False]


def set_value_checks(on_gpu: bool) -> None:
    """Check input values (finite, non-negative scales) also for GPU tensors (a debugging switch)."""
    _VALUE_CHECKS_ON_GPU[0] = bool(on_gpu)


def _checks_values(tensor: Tensor) -> bool:
    return tensor.device.type == "cpu" or _VALUE_CHECKS_ON_GPU[0]


class RasterOutput(NamedTuple):
    """features (C,F,H,W) with background composited, alpha (C,1,H,W) = 1 - final transmittance,
    depth (C,1,H,W) expected camera-space z ``Σ wᵢzᵢ / max(α, 1e-10)`` (0 where nothing was drawn)."""

    features: Tensor
    alpha: Tensor
    depth: Tensor


def _check_tensor(name: str, tensor: Tensor, shape: tuple) -> None:
    """Raise a ValueError naming the tensor when its shape (None = any size) or values are wrong."""
    if not isinstance(tensor, Tensor):
        raise TypeError(f"rasterize: {name} must be a torch.Tensor, got {type(tensor).__name__}")
    if tensor.dim() != len(shape) or any(
        s is not None and s != t for s, t in zip(shape, tensor.shape, strict=True)
    ):
        wanted = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"rasterize: {name} must have shape {wanted}, got {tuple(tensor.shape)}")
    if not tensor.is_floating_point():
        raise ValueError(f"rasterize: {name} must be a floating-point tensor, got {tensor.dtype}")
    if _checks_values(tensor) and not bool(torch.isfinite(tensor).all()):
        bad = "NaN" if bool(torch.isnan(tensor).any()) else "infinite"
        raise ValueError(f"rasterize: {name} contains {bad} values; check the upstream computation or data")


def select_backend(backend: str, means: Tensor) -> str:
    """Resolve ``"auto"`` to the fastest available backend for these tensors."""
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")
    if backend != "auto":
        return backend
    if means.is_cuda:
        return "gsplat" if gsplat_cuda_available() else "torch"
    if means.dtype == torch.float32:
        if tile_kernel_available():
            return "cpp"
    return "torch"


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    w2c: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    mode: str = "classic",
    near: float = 0.01,
    far: float = 1e10,
    backend: str = "auto",
    *,
    eps2d: float = 0.3,
    tile_size: int = 16,
) -> RasterOutput:
    """Render N Gaussians into C cameras.

    Args:
        means: (N,3) world positions (m). quats: (N,4) rotations, w x y z (need not be normalised).
        scales: (N,3) linear standard deviations (not log). opacities: (N,) in [0, 1].
        features: (N,F) or (C,N,F) per-Gaussian features (any F; per-camera for view-dependent colour).
        w2c: (C,4,4) world-to-camera, OpenCV axes. K: (C,3,3) intrinsics, pixel centre (u, v) at (u, v).
        width, height: image size in pixels. background: (F,) or (C,F), default zeros.
        mode: "classic" or "antialiased" (opacity × sqrt(det Σ / det(Σ + eps2d·I)), Mip-Splatting style).
        near, far: camera-space z range kept. backend: see the module docstring.

    Returns:
        RasterOutput(features (C,F,H,W), alpha (C,1,H,W), depth (C,1,H,W)).
    """
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")
    if mode not in MODES:
        raise ValueError(f"rasterize: mode must be one of {MODES}, got {mode!r}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"rasterize: width and height must be positive, got {width}x{height}")
    width, height = int(width), int(height)
    _check_tensor("means", means, (None, 3))
    N = means.shape[0]
    _check_tensor("w2c", w2c, (None, 4, 4))
    C = w2c.shape[0]
    _check_tensor("quats", quats, (N, 4))
    _check_tensor("scales", scales, (N, 3))
    _check_tensor("opacities", opacities, (N,))
    _check_tensor("K", K, (C, 3, 3))
    if features.dim() == 2:
        _check_tensor("features", features, (N, None))
        features = features[None].expand(C, N, features.shape[1])
    else:
        _check_tensor("features", features, (C, N, None))
    F = features.shape[-1]
    if background is None:
        background = torch.zeros(C, F, dtype=features.dtype, device=features.device)
    elif background.dim() == 1:
        _check_tensor("background", background, (F,))
        background = background[None].expand(C, F)
    else:
        _check_tensor("background", background, (C, F))
    if _checks_values(scales) and bool((scales < 0).any()):
        raise ValueError("rasterize: scales must be non-negative standard deviations (pass exp(log_scales))")

    chosen = select_backend(backend, means)
    if chosen == "cpp" and means.device.type != "cpu":
        raise ValueError(
            f"rasterize: backend 'cpp' runs on the CPU, got tensors on {means.device}; use 'auto'"
        )
    if chosen == "cpp" and tile_size != 16:
        raise ValueError(f"rasterize: backend 'cpp' uses 16x16 tiles, got tile_size={tile_size}")
    if chosen == "gsplat":
        if not (means.is_cuda and gsplat_cuda_available()):
            raise ValueError(
                "rasterize: backend 'gsplat' needs CUDA tensors and gsplat (pip install 'relightanyone[cuda]'); "
                "use backend='auto' to fall back to the CPU backends"
            )
    if chosen == "gsplat":
        return RasterOutput(
            *rasterize_gsplat(
                means,
                quats,
                scales,
                opacities,
                features,
                w2c,
                K,
                width,
                height,
                background,
                mode,
                near,
                far,
                eps2d,
                tile_size,
            )
        )

    compiled = rasterize_cpp if chosen == "cpp" and rasterize_cpp.load_tile_kernel() is not None else None
    # The fused compiled projection has no camera gradients: optimised cameras take the PyTorch projection.
    fused = (
        compiled is not None and means.dtype == torch.float32 and not (w2c.requires_grad or K.requires_grad)
    )
    project = compiled.project_gaussians_cpp if fused else project_gaussians
    projection = project(
        means, quats, scales, opacities, w2c, K, width, height, mode=mode, eps2d=eps2d, near=near, far=far
    )
    # Depth is composited as one more channel (with a zero background), like gsplat's "RGB+ED".
    colors = torch.cat([features, projection.depths[..., None].to(features.dtype)], dim=-1)
    background_ext = torch.cat([background, background.new_zeros(C, 1)], dim=-1)
    if chosen == "dense":
        image, alpha = composite_dense(projection, colors, background_ext, width, height)
    else:
        if compiled is not None:
            bins = compiled.bin_gaussians_to_tiles_cpp(
                projection.means2d, projection.radii, projection.depths, width, height, tile_size
            )
            image, alpha = compiled.composite_tiles_cpp(
                projection, colors, background_ext, bins, width, height
            )
        else:
            bins = bin_gaussians_to_tiles(
                projection.means2d, projection.radii, projection.depths, width, height, tile_size
            )
            image, alpha = composite_tiles_torch(projection, colors, background_ext, bins, width, height)
    image = image.permute(0, 3, 1, 2)
    alpha = alpha[:, None]
    depth = image[:, F:] / torch.clamp(alpha, min=1e-10)
    return RasterOutput(image[:, :F], alpha, depth)


def rasterize_batched(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    w2c: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    mode: str = "classic",
    backend: str = "auto",
) -> RasterOutput:
    """Render B Gaussian sets, set ``b`` into its own C cameras ``w2c[b]``, ``K[b]``.

    Args:
        means (B,N,3), quats (B,N,4), scales (B,N,3), opacities (B,N), features (B,N,F) or (B,C,N,F);
        w2c (B,C,4,4), K (B,C,3,3); background (F,) or (B,C,F). The rest as :func:`rasterize`.

    Returns:
        RasterOutput with features (B,C,F,H,W), alpha (B,C,1,H,W), depth (B,C,1,H,W).
    """
    batch = means.shape[0]
    if means.dim() != 3 or w2c.dim() != 4 or K.dim() != 4 or w2c.shape[0] != batch or K.shape[0] != batch:
        raise ValueError(
            f"rasterize_batched: means (B, N, 3) and cameras (B, C, 4, 4), (B, C, 3, 3) must share B; got "
            f"{tuple(means.shape)}, {tuple(w2c.shape)}, {tuple(K.shape)}"
        )
    if select_backend(backend, means) == "gsplat":
        cameras = w2c.shape[1]
        channels = features.shape[-1]
        if background is None:
            background = features.new_zeros(batch, cameras, channels)
        elif background.dim() == 1:
            background = background.expand(batch, cameras, channels)
        image, alpha, depth = rasterize_gsplat(
            means,
            quats,
            scales,
            opacities,
            features,
            w2c,
            K,
            int(width),
            int(height),
            background,
            mode,
            0.01,
            1e10,
            0.3,
            16,
        )
        return RasterOutput(image, alpha, depth)
    outputs = []
    for b in range(batch):
        sample_background = background if background is None or background.dim() == 1 else background[b]
        outputs.append(
            rasterize(
                means[b],
                quats[b],
                scales[b],
                opacities[b],
                features[b],
                w2c[b],
                K[b],
                width,
                height,
                background=sample_background,
                mode=mode,
                backend=backend,
            )
        )
    return RasterOutput(*(torch.stack(parts) for parts in zip(*outputs, strict=True)))
