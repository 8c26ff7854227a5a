"""The 3D Gaussian Splatting PLY: the de-facto exchange format that splat viewers and editors open.

One ``vertex`` element, binary little endian, every property ``float``, in this order:

=====================  ==========================================================================
``x y z``              centre (metres, canonical head space)
``nx ny nz``           zeros (the reference trainer writes them; viewers ignore them)
``f_dc_0 .. f_dc_2``   SH degree-0 coefficient per RGB channel: ``f_dc = (colour - 0.5) / C0``
``f_rest_0 ..``        higher SH bands, ``3 ((degree + 1)^2 - 1)`` values (45 for degree 3), channel-major:
                       all R coefficients, then all G, then all B
``opacity``            logit of the opacity
``scale_0 .. scale_2``  log of the standard deviations (metres)
``rot_0 .. rot_3``     unit quaternion, w x y z
=====================  ==========================================================================

``C0 = 0.28209479177387814`` is the degree-0 real SH constant; a viewer computes the colour as
``C0 · f_dc + 0.5`` (plus the higher bands) and clamps it to [0, 1].
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from relightanyone.errors import InputError

SH_C0 = 0.28209479177387814
MAX_SH_DEGREE = 3
# Opacities are stored as logits: exact 0 or 1 would become infinite, so they are kept this far inside.
OPACITY_EPS = 1e-7


def sh_rest_count(sh_degree: int) -> int:
    """Number of ``f_rest_*`` properties of an SH degree (0 for degree 0, 45 for degree 3)."""
    if not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in [0, {MAX_SH_DEGREE}], got {sh_degree}")
    return 3 * ((sh_degree + 1) ** 2 - 1)


def gaussian_ply_properties(sh_degree: int = 3) -> list[str]:
    """Property names of the vertex element, in file order."""
    return [
        "x",
        "y",
        "z",
        "nx",
        "ny",
        "nz",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        *(f"f_rest_{i}" for i in range(sh_rest_count(sh_degree))),
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]


def colours_to_sh_dc(colours: torch.Tensor) -> torch.Tensor:
    """(N, 3) colours -> (N, 3) degree-0 SH coefficients, ``(c - 0.5) / C0``."""
    return (colours - 0.5) / SH_C0


def sh_dc_to_colours(dc: torch.Tensor) -> torch.Tensor:
    """(N, 3) degree-0 SH coefficients -> (N, 3) colours, ``C0 · dc + 0.5`` (not clamped)."""
    return dc * SH_C0 + 0.5


def _as_array(name: str, value, shape: tuple) -> np.ndarray:
    array = np.asarray(torch.as_tensor(value).detach().cpu().double().numpy())
    if array.ndim != len(shape) or any(
        s is not None and a != s for a, s in zip(array.shape, shape, strict=True)
    ):
        wanted = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"write_gaussian_ply: {name} must be {wanted}, got {tuple(array.shape)}")
    if not np.isfinite(array).all():
        raise ValueError(f"write_gaussian_ply: {name} has NaN or infinite values")
    return array


def write_gaussian_ply(
    path: str | Path,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colours: torch.Tensor,
    sh_degree: int = 3,
) -> Path:
    """Write Gaussians as a standard 3DGS PLY (binary little endian), atomically.

    Args:
        path: output file (``.ply``).
        means: (N, 3) metres. quats: (N, 4) w x y z (normalized on writing). scales: (N, 3) standard
            deviations (> 0). opacities: (N,) in [0, 1]. colours: (N, 3) in the colour space the viewer
            should show (see ``docs/avatars.md``); values outside [0, 1] are kept (viewers clamp).
        sh_degree: SH degree the file declares; the bands above 0 are written as zeros.
    Returns:
        The path written.
    """
    from plyfile import PlyData, PlyElement

    path = Path(path)
    means_np = _as_array("means", means, (None, 3))
    count = means_np.shape[0]
    quats_np = _as_array("quats", quats, (count, 4))
    scales_np = _as_array("scales", scales, (count, 3))
    opacities_np = _as_array("opacities", opacities, (count,))
    colours_np = _as_array("colours", colours, (count, 3))
    if (scales_np <= 0).any():
        raise ValueError(
            "write_gaussian_ply: scales must be positive standard deviations (they are stored as logs)"
        )
    if ((opacities_np < 0) | (opacities_np > 1)).any():
        raise ValueError("write_gaussian_ply: opacities must be in [0, 1] (they are stored as logits)")
    norms = np.linalg.norm(quats_np, axis=1, keepdims=True)
    if (norms == 0).any():
        raise ValueError("write_gaussian_ply: quats has zero-length rotations")
    opacities_np = np.clip(opacities_np, OPACITY_EPS, 1.0 - OPACITY_EPS)
    names = gaussian_ply_properties(sh_degree)
    columns = {
        "x": means_np[:, 0],
        "y": means_np[:, 1],
        "z": means_np[:, 2],
        "opacity": np.log(opacities_np) - np.log1p(-opacities_np),
    }
    dc = (colours_np - 0.5) / SH_C0
    log_scales = np.log(scales_np)
    unit = quats_np / norms
    for axis in range(3):
        columns[f"f_dc_{axis}"] = dc[:, axis]
        columns[f"scale_{axis}"] = log_scales[:, axis]
    for axis in range(4):
        columns[f"rot_{axis}"] = unit[:, axis]
    vertices = np.zeros(count, dtype=[(name, "<f4") for name in names])  # normals and f_rest stay zero
    for name, values in columns.items():
        vertices[name] = values
    data = PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<")
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "wb") as handle:
        data.write(handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)
    return path


def read_gaussian_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY (ours or another tool's) into activated float32 tensors.

    Returns:
        means (N, 3); quats (N, 4) unit w x y z; scales (N, 3) = exp(scale_*); opacities (N,) =
        sigmoid(opacity); colours (N, 3) = C0 · f_dc + 0.5 (unclamped); sh_rest (N, K, 3) the higher
        bands (K = 0 for degree 0); normals (N, 3) (zeros when the file has none).
    """
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such PLY file")
    try:
        ply = PlyData.read(str(path))
    except (PlyParseError, ValueError, OSError, EOFError) as error:
        raise InputError(f"{path}: not a readable PLY file ({error})") from error
    if "vertex" not in ply:
        raise InputError(f"{path}: no 'vertex' element; a Gaussian PLY stores one Gaussian per vertex")
    vertex = ply["vertex"].data
    present = set(vertex.dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", *(f"scale_{i}" for i in range(3))]
    required += [f"rot_{i}" for i in range(4)]
    missing = [name for name in required if name not in present]
    if missing:
        raise InputError(f"{path}: vertex element lacks Gaussian properties {missing}")
    rest_names = sorted((n for n in present if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    if len(rest_names) % 3:
        raise InputError(f"{path}: {len(rest_names)} f_rest properties is not a multiple of 3 (RGB)")

    def stack(names: list[str]) -> torch.Tensor:
        if not names:
            return torch.zeros(len(vertex), 0)
        return torch.from_numpy(np.stack([np.asarray(vertex[n], dtype=np.float32) for n in names], axis=1))

    quats = stack([f"rot_{i}" for i in range(4)])
    normals = stack(["nx", "ny", "nz"]) if {"nx", "ny", "nz"} <= present else torch.zeros(len(vertex), 3)
    per_channel = len(rest_names) // 3
    return {
        "means": stack(["x", "y", "z"]),
        "quats": quats / quats.norm(dim=1, keepdim=True).clamp(min=1e-12),
        "scales": stack([f"scale_{i}" for i in range(3)]).exp(),
        "opacities": torch.sigmoid(stack(["opacity"])[:, 0]),
        "colours": sh_dc_to_colours(stack([f"f_dc_{i}" for i in range(3)])),
        # Channel-major on disk (R coefficients, then G, then B): (N, 3, K) -> (N, K, 3).
        "sh_rest": stack(rest_names).reshape(len(vertex), 3, per_channel).transpose(1, 2).contiguous(),
        "normals": normals,
    }
