"""Assembling 3D Gaussians from decoder UV maps bound to a mesh.

One Gaussian per valid UV texel. Its centre is the barycentric point of the decoded mesh at that texel
plus a learned offset δt (head space, as in RGCA, no tangent frame). Lengths the decoders predict
(offsets, scales) are in units of the *texel spacing* — the side of the patch of surface one texel
covers — so the same initialisation and regularisers work at UV 64² and at UV 1024².

Channel layout of the geometry map (11 channels): δt (3), rotation quaternion w x y z (4), log-ish scale
(3), opacity logit (1). The colour map has 3 channels (linear RGB, full-on light).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from relightanyone.errors import InputError
from relightanyone.model.networks.presets import Stage1Preset
from relightanyone.render.mesh import load_obj
from relightanyone.render.uv_binding import UVBinding

GEOMETRY_CHANNELS = 11
COLOUR_CHANNELS = 3
# Scales outside [MIN_SCALE, MAX_SCALE] texel spacings are clamped and penalised by the scale regulariser.
MIN_SCALE = 0.02
MAX_SCALE = 10.0
INITIAL_SCALE = 0.6  # texel spacings: neighbouring Gaussians overlap a little at start
INITIAL_OPACITY = 0.88
INITIAL_COLOUR = 0.3  # linear grey, roughly a skin tone's luminance under full-on light
_SOFTPLUS_ZERO = math.log(2.0)


def geometry_output_bias() -> torch.Tensor:
    """(11,) initial geometry-map value: no offset, identity rotation, INITIAL_SCALE, INITIAL_OPACITY."""
    scale_raw = math.log(math.expm1(INITIAL_SCALE * _SOFTPLUS_ZERO))
    opacity_raw = math.log(INITIAL_OPACITY / (1.0 - INITIAL_OPACITY))
    return torch.tensor(
        [0, 0, 0, 1, 0, 0, 0, scale_raw, scale_raw, scale_raw, opacity_raw], dtype=torch.float32
    )


def colour_output_bias() -> torch.Tensor:
    """(3,) initial colour-map value."""
    return torch.full((COLOUR_CHANNELS,), INITIAL_COLOUR)


@dataclass
class TexelBinding:
    """Which mesh triangle and barycentric point each valid UV texel sits on.

    valid_index: (N,) int64 flat indices (row * S + column) of the valid texels, in raster order.
    texel_faces: (N,) int64 triangle of each valid texel.
    texel_barycentrics: (N, 3) float32 barycentric weights of the texel centre in that triangle.
    faces: (F, 3) int64 vertex indices (tracked-mesh topology).
    uv_size: S.
    """

    valid_index: torch.Tensor
    texel_faces: torch.Tensor
    texel_barycentrics: torch.Tensor
    faces: torch.Tensor
    uv_size: int

    @classmethod
    def from_maps(
        cls, face_index: torch.Tensor, barycentrics: torch.Tensor, valid: torch.Tensor, faces: torch.Tensor
    ) -> TexelBinding:
        """From UV maps: face_index (S, S) int, barycentrics (S, S, 3), valid (S, S) bool, faces (F, 3)."""
        face_index = torch.as_tensor(face_index)
        size = face_index.shape[-1]
        if face_index.shape != (size, size) or tuple(barycentrics.shape) != (size, size, 3):
            raise ValueError(
                f"UV binding maps must be (S, S) and (S, S, 3); got {tuple(face_index.shape)} "
                f"and {tuple(barycentrics.shape)}"
            )
        valid_flat = torch.as_tensor(valid).reshape(-1).bool()
        if not bool(valid_flat.any()):
            raise InputError("UV binding has no valid texel: the template mesh's UVs cover no texel centre")
        valid_index = torch.nonzero(valid_flat).squeeze(1)
        return cls(
            valid_index=valid_index,
            texel_faces=face_index.reshape(-1)[valid_index].long(),
            texel_barycentrics=torch.as_tensor(barycentrics, dtype=torch.float32).reshape(-1, 3)[valid_index],
            faces=torch.as_tensor(faces).long(),
            uv_size=size,
        )

    @property
    def count(self) -> int:
        return int(self.valid_index.numel())


def texel_positions(vertices: torch.Tensor, binding: TexelBinding) -> torch.Tensor:
    """Barycentric surface point of every valid texel: vertices (B, V, 3) -> (B, N, 3)."""
    device = vertices.device  # the binding may live on the CPU while the decoders run on a GPU
    corners = binding.faces.to(device)[binding.texel_faces.to(device)]  # (N, 3) vertex ids
    triangle_points = vertices[:, corners]  # (B, N, 3 corners, 3 xyz)
    barycentrics = binding.texel_barycentrics.to(vertices)
    return (triangle_points * barycentrics[None, :, :, None]).sum(dim=2)


def gather_texels(uv_maps: torch.Tensor, binding: TexelBinding) -> torch.Tensor:
    """Values at the valid texels: uv_maps (B, C, S, S) -> (B, N, C)."""
    batch, channels = uv_maps.shape[:2]
    valid_index = binding.valid_index.to(uv_maps.device)
    return uv_maps.reshape(batch, channels, -1)[:, :, valid_index].transpose(1, 2)


def load_template_binding(template_path: Path, uv_size: int) -> tuple[torch.Tensor, TexelBinding]:
    """The template mesh of a run or dataset: its vertices (V, 3) float32 and its valid texels at ``uv_size``²."""
    mesh = load_obj(template_path)
    uv = UVBinding.from_mesh(mesh.vertices, mesh.faces, mesh.uvs, mesh.face_uvs, uv_size)
    binding = TexelBinding.from_maps(uv.face_index, uv.barycentrics, uv.valid, uv.faces)
    return torch.from_numpy(mesh.vertices).float(), binding


def bind_template(
    preset: Stage1Preset, template_vertices: torch.Tensor, binding: TexelBinding
) -> tuple[torch.Tensor, float]:
    """Check that ``binding`` has the preset's UV size; the template (V, 3) as float32 and its texel spacing."""
    if binding.uv_size != preset.uv_size:
        raise ValueError(
            f"UV binding is {binding.uv_size}² but preset {preset.name!r} needs {preset.uv_size}²"
        )
    template_vertices = torch.as_tensor(template_vertices, dtype=torch.float32)
    return template_vertices, texel_spacing(template_vertices, binding.faces, binding.count)


def texel_spacing(vertices: torch.Tensor, faces: torch.Tensor, valid_texels: int) -> float:
    """Side in metres of the surface patch one valid texel covers: sqrt(mesh area / texel count).

    vertices (V, 3), faces (F, 3).
    """
    corners = vertices[faces.long()]
    area = (
        0.5
        * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=-1).sum()
    )
    if valid_texels <= 0 or float(area) <= 0:
        raise ValueError("cannot derive a texel spacing from an empty mesh or an empty UV binding")
    return math.sqrt(float(area) / valid_texels)


@dataclass
class Gaussians:
    """A batch of Gaussian sets, one per sample, all with N Gaussians.

    means (B, N, 3) metres; quats (B, N, 4) unit, w x y z; scales (B, N, 3) metres, clamped;
    opacities (B, N) in (0, 1); colours (B, N, 3) linear RGB >= 0;
    offsets (B, N, 3) δt in texel spacings; scales_preclip (B, N, 3) scales in texel spacings before the
    clamp (what the scale regulariser sees).
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colours: torch.Tensor
    offsets: torch.Tensor
    scales_preclip: torch.Tensor

    def sample(self, index: int) -> Gaussians:
        """The Gaussians of one sample, keeping a leading batch dimension of 1."""
        return Gaussians(**{name: value[index : index + 1] for name, value in vars(self).items()})


def assemble_gaussians(
    geometry_maps: torch.Tensor,
    colour_maps: torch.Tensor,
    vertices: torch.Tensor,
    binding: TexelBinding,
    spacing: float,
) -> Gaussians:
    """Decoder outputs to Gaussians.

    Args:
        geometry_maps: (B, 11, S, S) raw D_g output (δt, quaternion, scale, opacity logit).
        colour_maps: (B, 3, S, S) raw D_c output.
        vertices: (B, V, 3) decoded mesh (metres).
        binding: valid texels and their triangles.
        spacing: texel spacing in metres (see :func:`texel_spacing`).
    """
    if geometry_maps.shape[1] != GEOMETRY_CHANNELS or colour_maps.shape[1] != COLOUR_CHANNELS:
        raise ValueError(
            f"expected {GEOMETRY_CHANNELS} geometry and {COLOUR_CHANNELS} colour channels, got "
            f"{geometry_maps.shape[1]} and {colour_maps.shape[1]}"
        )
    raw = gather_texels(geometry_maps, binding)
    offsets = raw[..., 0:3]
    quats = F.normalize(raw[..., 3:7], dim=-1)
    scales_preclip = F.softplus(raw[..., 7:10]) / _SOFTPLUS_ZERO
    scales = scales_preclip.clamp(MIN_SCALE, MAX_SCALE) * spacing
    opacities = torch.sigmoid(raw[..., 10])
    colours = gather_texels(colour_maps, binding).clamp(min=0.0)
    means = texel_positions(vertices, binding) + offsets * spacing
    return Gaussians(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colours=colours,
        offsets=offsets,
        scales_preclip=scales_preclip,
    )
