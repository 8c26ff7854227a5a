"""Environment maps: lat-long I/O, orientation, SH and directional-light conversion, SG-prefiltered mips.

Orientation (canonical head space: +y up, +z out of the face, +x the subject's left):

* An environment map is an equirectangular ``(3, H, W)`` float32 tensor of linear radiance arriving at the
  subject *from* each direction. Row 0 is straight up (+y), the last row straight down.
* Texel ``(row i, column j)`` has polar angle ``theta = pi (i + 0.5) / H`` from +y and azimuth
  ``phi = 2 pi ((j + 0.5) / W - 0.5)`` with direction ``(sin(theta) sin(phi), cos(theta), sin(theta) cos(phi))``.
* So the **centre column** (``u = 0.5``) faces the subject's front (+z); columns increase towards +x, the
  subject's left, at ``u = 0.75``; ``u = 0.25`` is the subject's right (-x) and both edges are behind (-z).
  This is goliath's ``dir2uv`` (``u = atan2(x, z) / pi`` in [-1, 1]).
* :func:`rotate_envmap_yaw` by ``+angle`` turns the environment counter-clockwise seen from above (+z towards
  +x): a light in front moves to the subject's left for +90 degrees, i.e. the image shifts right by ``W/4``.

Every conversion here (SH, directional lights, prefiltering, lookup) uses these same formulas.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from relightanyone.render.errors import FileFormatError
from relightanyone.render.lights import DirectionalLights
from relightanyone.render.sh import project_directions_to_sh


def latlong_directions(height: int, width: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(H, W, 3)`` unit directions of the texel centres (see the module docstring)."""
    theta = math.pi * (torch.arange(height, dtype=torch.float64) + 0.5) / height
    phi = 2.0 * math.pi * ((torch.arange(width, dtype=torch.float64) + 0.5) / width - 0.5)
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    dirs = torch.stack(
        [torch.sin(theta) * torch.sin(phi), torch.cos(theta), torch.sin(theta) * torch.cos(phi)], -1
    )
    return dirs.to(dtype)


def latlong_solid_angles(height: int, width: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(H, W)`` exact solid angle of each texel (they sum to ``4 pi``)."""
    edges = torch.cos(math.pi * torch.arange(height + 1, dtype=torch.float64) / height)
    per_row = (edges[:-1] - edges[1:]) * (2.0 * math.pi / width)
    return per_row[:, None].expand(height, width).to(dtype)


def direction_to_latlong_uv(dirs: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` directions -> ``(..., 2)`` lat-long coordinates ``(u, v)`` in [0, 1], u right, v down."""
    unit = F.normalize(dirs, dim=-1)
    u = 0.5 + torch.atan2(unit[..., 0], unit[..., 2]) / (2.0 * math.pi)
    v = torch.acos(unit[..., 1].clamp(-1.0, 1.0)) / math.pi
    return torch.stack([u, v], dim=-1)


def yaw_rotation_matrix(angle_rad: float | torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` right-handed rotation about +y by ``angle`` (+z turns towards +x for positive angles)."""
    angle = torch.as_tensor(angle_rad, dtype=torch.float32)
    cos, sin = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(angle), torch.ones_like(angle)
    rows = [
        torch.stack([cos, zero, sin], -1),
        torch.stack([zero, one, zero], -1),
        torch.stack([-sin, zero, cos], -1),
    ]
    return torch.stack(rows, dim=-2)


def rotate_envmap_yaw(env: torch.Tensor, angle_rad: float) -> torch.Tensor:
    """Turn an environment about the vertical axis: ``rotated(R d) = env(d)`` with ``R = yaw_rotation_matrix``.

    A rotation by ``angle`` is a circular shift of the columns by ``angle / (2 pi) * W`` to the right;
    fractional shifts interpolate linearly between neighbouring columns.

    Args:
        env: ``(..., 3, H, W)``.
        angle_rad: rotation angle in radians.

    Returns:
        ``(..., 3, H, W)``.
    """
    width = env.shape[-1]
    shift = (angle_rad / (2.0 * math.pi) * width) % width
    whole = math.floor(shift)
    fraction = shift - whole
    shifted = torch.roll(env, shifts=whole, dims=-1)
    if fraction < 1e-9:
        return shifted
    return (1.0 - fraction) * shifted + fraction * torch.roll(shifted, shifts=1, dims=-1)


def envmap_to_sh(env: torch.Tensor, order: int) -> torch.Tensor:
    """Project radiance onto SH by exact-solid-angle quadrature: ``L_lm = sum env * Y_lm * dOmega``.

    Args:
        env: ``(3, H, W)`` (or ``(C, H, W)``) radiance.
        order: SH order.

    Returns:
        ``(C, (order + 1) ** 2)``.
    """
    channels, height, width = _check_env(env)
    dirs = latlong_directions(height, width, env.dtype).to(env.device).reshape(-1, 3)
    weights = env.reshape(channels, -1).T * latlong_solid_angles(height, width, env.dtype).to(
        env.device
    ).reshape(-1, 1)
    return project_directions_to_sh(dirs, weights, order)


def _row_overlap(src: int, dst: int) -> torch.Tensor:
    """``(dst, src)`` integral of sin(theta) d(theta) over the overlap of destination and source rows."""
    src_edges = torch.arange(src + 1, dtype=torch.float64) * math.pi / src
    dst_edges = torch.arange(dst + 1, dtype=torch.float64) * math.pi / dst
    top = torch.maximum(dst_edges[:-1, None], src_edges[None, :-1])
    bottom = torch.minimum(dst_edges[1:, None], src_edges[None, 1:])
    return torch.where(bottom > top, torch.cos(top) - torch.cos(bottom), torch.zeros(()))


def _column_overlap(src: int, dst: int) -> torch.Tensor:
    """``(dst, src)`` azimuth length of the overlap of destination and source columns."""
    src_edges = torch.arange(src + 1, dtype=torch.float64) * 2.0 * math.pi / src
    dst_edges = torch.arange(dst + 1, dtype=torch.float64) * 2.0 * math.pi / dst
    left = torch.maximum(dst_edges[:-1, None], src_edges[None, :-1])
    right = torch.minimum(dst_edges[1:, None], src_edges[None, 1:])
    return torch.clamp(right - left, min=0.0)


def integrate_blocks(env: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """Exact integral of radiance over each texel of a coarser (or finer) lat-long grid.

    Texels are treated as constant over their area, so the total ``sum(env * dOmega)`` is preserved.

    Args:
        env: ``(C, H, W)``.
        rows, cols: target grid.

    Returns:
        ``(C, rows, cols)`` radiance times solid angle.
    """
    _, height, width = _check_env(env)
    row_weights = _row_overlap(height, rows).to(env.device, env.dtype)
    col_weights = _column_overlap(width, cols).to(env.device, env.dtype)
    return torch.einsum("rh,chw,qw->crq", row_weights, env, col_weights)


def resample_envmap(env: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Area-weighted (solid-angle exact) resampling of a lat-long map to ``(C, height, width)``."""
    solid = latlong_solid_angles(height, width, env.dtype).to(env.device)
    return integrate_blocks(env, height, width) / solid


def envmap_to_directional_lights(env: torch.Tensor, rows: int = 10, cols: int = 20) -> DirectionalLights:
    """Reduce an environment to ``rows x cols`` directional lights (3DPR uses 10 x 20).

    Each light sits at its block's centre direction and carries the block's radiance integrated over its
    solid angle, so the lights deliver the environment's irradiance to a surface (up to block size).

    Returns:
        :class:`DirectionalLights` with ``rows * cols`` lights in row-major (top-left first) order.
    """
    channels, _, _ = _check_env(env)
    irradiance = integrate_blocks(env, rows, cols).reshape(channels, -1).T
    dirs = latlong_directions(rows, cols, env.dtype).to(env.device).reshape(-1, 3)
    return DirectionalLights(dirs, irradiance)


def sg_filter_envmap(env: torch.Tensor, sigma: float, row_chunk: int = 32) -> torch.Tensor:
    """Convolve a lat-long map with a normalised angular Gaussian ``exp(-theta^2 / (2 sigma^2))``.

    Exact (no sampling noise): the kernel between an output row and a source row depends only on the azimuth
    difference, so each output row is a sum over source rows of circular convolutions done by FFT. Each
    output texel is a weighted mean of radiance (weights sum to one), so a constant map stays constant.

    Args:
        env: ``(C, H, W)``.
        sigma: lobe width in radians (> 0).
        row_chunk: output rows per step (bounds memory to ``row_chunk * H * W``).

    Returns:
        ``(C, H, W)``.
    """
    if sigma <= 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    channels, height, width = _check_env(env)
    device = env.device
    theta = math.pi * (torch.arange(height, dtype=torch.float64, device=device) + 0.5) / height
    delta_phi = 2.0 * math.pi * torch.arange(width, dtype=torch.float64, device=device) / width
    solid = latlong_solid_angles(height, width, torch.float64).to(device)[:, 0]
    env_spectrum = torch.fft.rfft(env.to(torch.float64), dim=-1)  # (C, H, W/2+1)
    out = torch.empty(channels, height, width, dtype=torch.float64, device=device)
    for start in range(0, height, row_chunk):
        rows = theta[start : start + row_chunk]
        cos_angle = (
            torch.cos(rows)[:, None, None] * torch.cos(theta)[None, :, None]
            + torch.sin(rows)[:, None, None]
            * torch.sin(theta)[None, :, None]
            * torch.cos(delta_phi)[None, None, :]
        )
        angle = torch.acos(cos_angle.clamp(-1.0, 1.0))
        kernel = torch.exp(-0.5 * (angle / sigma) ** 2) * solid[None, :, None]  # (r, H, W)
        kernel = kernel / kernel.sum(dim=(1, 2), keepdim=True)
        # Circular correlation along azimuth == convolution here, since the kernel is even in delta_phi.
        spectrum = torch.einsum("rhf,chf->crf", torch.fft.rfft(kernel, dim=-1), env_spectrum)
        out[:, start : start + row_chunk] = torch.fft.irfft(spectrum, n=width, dim=-1)
    return out.to(env.dtype).clamp_min(0.0)


@dataclass(frozen=True)
class PrefilteredEnvmap:
    """Mip chain of SG-prefiltered lat-long maps for specular lookups (RGCA §3.1).

    Level ``k`` holds the environment convolved with a normalised angular Gaussian of width
    ``k * sigma_step`` (level 0 is the unfiltered map), at half the previous resolution.

    Attributes:
        levels: list of ``(3, H_k, W_k)`` tensors.
        sigma_step: lobe width (radians) between consecutive levels.
    """

    levels: tuple[torch.Tensor, ...]
    sigma_step: float

    def sample(self, dirs: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """Prefiltered radiance around ``dirs`` for lobe width ``sigma``, differentiable in both.

        Bilinear within a level (wrapping in azimuth), linear between the two nearest levels; widths beyond
        the last level use the last level.

        Args:
            dirs: ``(..., 3)`` lookup directions (e.g. reflected view directions) in environment space.
            sigma: ``(...)`` lobe widths in radians.

        Returns:
            ``(..., 3)``.
        """
        shape = dirs.shape[:-1]
        uv = direction_to_latlong_uv(dirs.reshape(-1, 3))
        level = (sigma.reshape(-1) / self.sigma_step).clamp(0.0, len(self.levels) - 1)
        result = dirs.new_zeros(uv.shape[0], self.levels[0].shape[0])
        for index, texture in enumerate(self.levels):
            weight = torch.clamp(1.0 - (level - index).abs(), min=0.0)
            if not bool((weight > 0).any()):
                continue
            result = result + weight[:, None] * _sample_wrapped(texture.to(dirs.dtype), uv)
        return result.reshape(*shape, -1)


def prefilter_envmap(
    env: torch.Tensor, num_levels: int = 4, sigma_step: float = 0.2, base_height: int = 256
) -> PrefilteredEnvmap:
    """Build the specular mip chain (RGCA: 4 levels, sigma 0 / 0.2 / 0.4 / 0.6).

    Args:
        env: ``(3, H, W)`` radiance.
        num_levels: number of levels (>= 1).
        sigma_step: lobe width step in radians.
        base_height: height of level 0 (width ``2 * base_height``); the map is area-resampled to it.

    Returns:
        :class:`PrefilteredEnvmap`.
    """
    if num_levels < 1:
        raise ValueError(f"num_levels must be >= 1, got {num_levels}")
    if base_height >> (num_levels - 1) < 2:
        raise ValueError(f"base_height {base_height} is too small for {num_levels} levels")
    _check_env(env)
    levels = [resample_envmap(env, base_height, 2 * base_height)]
    for index in range(1, num_levels):
        height = base_height >> index
        levels.append(sg_filter_envmap(resample_envmap(env, height, 2 * height), index * sigma_step))
    return PrefilteredEnvmap(levels=tuple(levels), sigma_step=sigma_step)


def _sample_wrapped(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of ``(C, H, W)`` at ``(N, 2)`` lat-long ``uv``, wrapping in u, clamping in v -> ``(N, C)``."""
    _, height, width = texture.shape
    padded = torch.cat([texture[..., -1:], texture, texture[..., :1]], dim=-1)
    # Texel centre j sits at u = (j + 0.5) / W; in the padded texture it is column j + 1.
    column = uv[:, 0] * width - 0.5 + 1.0
    grid_x = (column + 0.5) / (width + 2) * 2.0 - 1.0
    grid_y = uv[:, 1] * 2.0 - 1.0
    grid = torch.stack([grid_x, grid_y], dim=-1)[None, :, None, :]
    sampled = F.grid_sample(padded[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[0, :, :, 0].T


def load_envmap(path: str | Path) -> torch.Tensor:
    """Read a lat-long HDR environment (``.exr`` via OpenEXR, ``.hdr`` via OpenCV) as ``(3, H, W)`` float32.

    Negative values (from some HDR pipelines) are clamped to zero; NaN or infinity is an error.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: environment map not found")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        import OpenEXR

        with OpenEXR.File(str(path), separate_channels=False) as exr:
            channels = exr.channels()
            if "RGB" in channels:
                pixels = np.asarray(channels["RGB"].pixels, dtype=np.float32)
            elif "RGBA" in channels:
                pixels = np.asarray(channels["RGBA"].pixels, dtype=np.float32)[..., :3]
            elif "Y" in channels:
                pixels = np.repeat(np.asarray(channels["Y"].pixels, dtype=np.float32)[..., None], 3, axis=-1)
            else:
                raise FileFormatError(
                    f"{path}: no RGB, RGBA or Y channels in the EXR (found {sorted(channels)})"
                )
    elif suffix in (".hdr", ".pic"):
        import cv2

        bgr = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileFormatError(f"{path}: OpenCV could not decode this Radiance HDR file")
        pixels = np.ascontiguousarray(bgr[..., ::-1], dtype=np.float32)
    else:
        raise FileFormatError(f"{path}: unsupported environment map format '{suffix}' (use .exr or .hdr)")
    if pixels.ndim != 3 or pixels.shape[0] < 2 or pixels.shape[1] < 2:
        raise FileFormatError(f"{path}: expected an H x W colour image, got shape {pixels.shape}")
    if not np.isfinite(pixels).all():
        raise FileFormatError(f"{path}: environment map has NaN or infinite values")
    return torch.from_numpy(np.clip(pixels, 0.0, None)).permute(2, 0, 1).contiguous()


def save_envmap(path: str | Path, env: torch.Tensor) -> None:
    """Write ``(3, H, W)`` radiance as float32 EXR (``.exr``) or Radiance RGBE (``.hdr``)."""
    path = Path(path)
    _check_env(env)
    pixels = np.ascontiguousarray(env.detach().cpu().permute(1, 2, 0).numpy(), dtype=np.float32)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        import OpenEXR

        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(header, {"RGB": pixels}).write(str(path))
    elif suffix == ".hdr":
        import cv2

        if not cv2.imwrite(str(path), np.ascontiguousarray(pixels[..., ::-1])):
            raise OSError(f"{path}: OpenCV could not write the HDR file")
    else:
        raise FileFormatError(f"{path}: unsupported environment map format '{suffix}' (use .exr or .hdr)")


def _check_env(env: torch.Tensor) -> tuple[int, int, int]:
    if not isinstance(env, torch.Tensor) or env.ndim != 3:
        shape = tuple(env.shape) if isinstance(env, torch.Tensor) else type(env).__name__
        raise ValueError(f"environment map must be a (C, H, W) tensor, got {shape}")
    return env.shape[0], env.shape[1], env.shape[2]
