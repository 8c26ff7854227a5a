"""Build, load and call the compiled C++/OpenMP rasterizer parts in ``render/csrc/``: projection
(``project_gaussians.cpp``), tile binning (``bin_tiles.cpp``) and the tile compositor (``rasterize_tiles.cpp``),
the differentiable ones with their exact backward.

The kernel is compiled on first use (``-O3 -march=native -fopenmp``) and cached by
:mod:`relightanyone.compiled`. When no compiler is available, :func:`load_tile_kernel` warns once and
returns ``None``; callers fall back to the PyTorch path.
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch
from torch import Tensor

from relightanyone.compiled import cache_dir, load_extension
from relightanyone.compiled import extension_name as _extension_name
from relightanyone.render.rasterize_torch import Projection, TileBins

__all__ = ["cache_dir", "extension_name", "load_tile_kernel", "tile_kernel_available"]

SOURCES = [
    Path(__file__).resolve().parent / "csrc" / name
    for name in ("rasterize_tiles.cpp", "project_gaussians.cpp", "bin_tiles.cpp")
]
# -ffast-math lets GCC vectorise the float reductions and selects of the row loops; it is a compile flag only
# (never linked, so the process' denormal handling is untouched).
CFLAGS = ["-O3", "-march=native", "-fopenmp", "-ffast-math", "-std=c++17"]
LDFLAGS = ["-fopenmp"]
PREFIX = "relightanyone_raster"


def extension_name() -> str:
    """Module name keyed by the source, the flags and the torch version."""
    return _extension_name(PREFIX, SOURCES, CFLAGS, LDFLAGS)


@functools.lru_cache(maxsize=1)
def load_tile_kernel():
    """The compiled module (``project_forward``/``project_backward``, ``bin_tiles``,
    ``composite_forward``/``composite_backward``), or ``None`` if it cannot be built."""
    return load_extension(PREFIX, SOURCES, CFLAGS, LDFLAGS, "rasterizer", "using the slower PyTorch path")


def tile_kernel_available() -> bool:
    """Whether the compiled CPU kernel can be used (builds it on first call)."""
    return load_tile_kernel() is not None


class _ProjectCompiled(torch.autograd.Function):
    """Autograd wrapper of the fused float32 projection; gradients for the Gaussian parameters only."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, w2c, K, width, height, eps2d, near, far, antialiased):
        inputs = [
            t.detach().to(torch.float32).contiguous() for t in (means, quats, scales, opacities, w2c, K)
        ]
        threads = torch.get_num_threads()
        settings = (width, height, eps2d, near, far, antialiased)
        means2d, conics, depths, opacities_cam, radii = load_tile_kernel().project_forward(
            *inputs, *settings, threads
        )
        ctx.save_for_backward(*inputs)
        ctx.settings = settings
        ctx.threads = threads
        ctx.dtypes = [t.dtype for t in (means, quats, scales, opacities)]
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, opacities_cam, radii

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_opacities, _v_radii):
        inputs = ctx.saved_tensors
        C, N = inputs[4].shape[0], inputs[0].shape[0]
        upstream = []
        for grad, shape in (
            (v_means2d, (C, N, 2)),
            (v_conics, (C, N, 3)),
            (v_depths, (C, N)),
            (v_opacities, (C, N)),
        ):
            upstream.append(
                inputs[0].new_zeros(shape) if grad is None else grad.to(torch.float32).contiguous()
            )
        grads = load_tile_kernel().project_backward(*inputs, *upstream, *ctx.settings, ctx.threads)
        grads = [g.to(dtype) for g, dtype in zip(grads, ctx.dtypes, strict=True)]
        return (*grads, None, None, None, None, None, None, None, None)


def project_gaussians_cpp(
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
    """Compiled equivalent of ``project_gaussians`` in float32 (one fused pass per Gaussian, OpenMP).

    means (N,3), quats (N,4) wxyz, scales (N,3), opacities (N,), w2c (C,4,4), K (C,3,3) → Projection.
    Differentiable in means, quats, scales and opacities; ``w2c`` and ``K`` get no gradient (use
    ``project_gaussians`` when the cameras are optimised).
    """
    if mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize mode must be 'classic' or 'antialiased', got {mode!r}")
    means2d, conics, depths, opacities_cam, radii = _ProjectCompiled.apply(
        means,
        quats,
        scales,
        opacities,
        w2c,
        K,
        int(width),
        int(height),
        float(eps2d),
        float(near),
        float(far),
        mode == "antialiased",
    )
    return Projection(means2d, conics, depths, opacities_cam, radii)


def bin_gaussians_to_tiles_cpp(
    means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = 16
) -> TileBins:
    """Compiled equivalent of ``bin_gaussians_to_tiles`` (same pairs, same order; needs the kernel).

    means2d (C,N,2), radii (C,N,2) int (0 = culled), depths (C,N), float32 or float64 on the CPU → TileBins.
    Counts, prefix sum and fill are serial passes over the Gaussians; each tile's list is then sorted by depth
    (stable, so ties keep the Gaussian order) in parallel.
    """
    dtype = torch.float64 if means2d.dtype == torch.float64 else torch.float32
    flatten_ids, tile_offsets = load_tile_kernel().bin_tiles(
        means2d.detach().to(dtype).contiguous(),
        radii.to(torch.int32).contiguous(),
        depths.detach().to(dtype).contiguous(),
        int(width),
        int(height),
        int(tile_size),
        torch.get_num_threads(),
    )
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    return TileBins(flatten_ids, tile_offsets, tiles_x, tiles_y, tile_size)


class _TileComposite(torch.autograd.Function):
    """Autograd wrapper: float32 kernel, gradients returned in the inputs' dtype."""

    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        colors,
        background,
        radii,
        tile_offsets,
        flatten_ids,
        width,
        height,
        tile_size,
    ):
        kernel = load_tile_kernel()
        inputs = [
            t.detach().to(torch.float32).contiguous()
            for t in (means2d, conics, opacities, colors, background)
        ]
        threads = torch.get_num_threads()
        image, transmittance, last = kernel.composite_forward(
            *inputs[:4], radii, inputs[4], tile_offsets, flatten_ids, width, height, tile_size, threads
        )
        ctx.save_for_backward(*inputs, radii, tile_offsets, flatten_ids, image, transmittance, last)
        ctx.frame = (width, height, tile_size, threads)
        ctx.dtypes = [t.dtype for t in (means2d, conics, opacities, colors, background)]
        ctx.mark_non_differentiable(last)
        alpha = 1.0 - transmittance
        dtype = colors.dtype
        return image.to(dtype), alpha.to(dtype), transmittance.to(dtype)

    @staticmethod
    def backward(ctx, grad_image, grad_alpha, grad_transmittance):
        saved = ctx.saved_tensors
        inputs, (radii, tile_offsets, flatten_ids, image, transmittance, last) = saved[:5], saved[5:]
        background = inputs[4]
        width, height, tile_size, threads = ctx.frame
        grad_image = (
            torch.zeros_like(image) if grad_image is None else grad_image.to(torch.float32).contiguous()
        )
        grad_alpha = torch.zeros_like(transmittance) if grad_alpha is None else grad_alpha.to(torch.float32)
        if grad_transmittance is not None:
            grad_alpha = grad_alpha - grad_transmittance.to(torch.float32)  # T = 1 - alpha
        grad_alpha = grad_alpha.contiguous()
        grads = load_tile_kernel().composite_backward(
            *inputs[:4],
            radii,
            background,
            tile_offsets,
            flatten_ids,
            image,
            transmittance,
            last,
            grad_image,
            grad_alpha,
            width,
            height,
            tile_size,
            threads,
        )
        C = background.shape[0]
        grad_background = (grad_image * transmittance[..., None]).reshape(C, -1, background.shape[1]).sum(1)
        out = [grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:], grad_background]
        out = [g.to(dtype) for g, dtype in zip(out, ctx.dtypes, strict=True)]
        return (*out, None, None, None, None, None, None)


def composite_tiles_cpp(
    projection: Projection, colors: Tensor, background: Tensor, bins: TileBins, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Composite with the compiled kernel (same contract as ``composite_tiles_torch``).

    colors (C,N,D), background (C,D) → (image (C,H,W,D), alpha (C,H,W)). Computes in float32.
    """
    C, N, D = colors.shape
    image, alpha, _ = _TileComposite.apply(
        projection.means2d.reshape(C * N, 2),
        projection.conics.reshape(C * N, 3),
        projection.opacities.reshape(C * N),
        colors.reshape(C * N, D),
        background,
        projection.radii.reshape(C * N, 2).to(torch.int32).contiguous(),
        bins.tile_offsets.to(torch.int64).contiguous(),
        bins.flatten_ids.to(torch.int64).contiguous(),
        width,
        height,
        bins.tile_size,
    )
    return image, alpha
