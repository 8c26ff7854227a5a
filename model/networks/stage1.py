"""The stage-1 network: per-subject identity codes, per-dataset lighting codes, three decoders.

``Stage1Model(z_id, z_l)`` gives the decoded mesh and one Gaussian per valid UV texel:

* ``D_mesh``: z_id → template-topology vertices,
* ``D_g``: z_id → UV maps of δt, rotation, scale, opacity (geometry never sees the lighting code, so
  swapping z_l cannot move a Gaussian),
* ``D_c``: [z_id, z_l] → full-on colour.

For the colour-alignment warm-up the lighting code is switched off (zeros) and the model carries one
learnable 3×3 per dataset, applied to the rendered image of datasets flagged uncalibrated:
``predicted_dataset_rgb = C_d @ rendered_rgb``.
"""

from __future__ import annotations

import torch
from torch import nn

from relightanyone.model.networks.decoders import ConvUVDecoder, MeshDecoder
from relightanyone.model.networks.gaussians import (
    COLOUR_CHANNELS,
    GEOMETRY_CHANNELS,
    Gaussians,
    TexelBinding,
    assemble_gaussians,
    bind_template,
    colour_output_bias,
    geometry_output_bias,
)
from relightanyone.model.networks.precision import run_maps
from relightanyone.model.networks.presets import Stage1Preset

CODE_INIT_STD = 0.1


class Stage1Model(nn.Module):
    """Multi-identity full-on Gaussian head model.

    Args:
        preset: sizes (UV size, code sizes, decoder widths).
        template_vertices: (V, 3) template mesh in canonical metres (initial D_mesh output).
        binding: valid UV texels of the template and their triangles (uv_size must match the preset).
        subject_count: number of identity codes (one per ``<dataset>/<subject>``).
        dataset_count: number of lighting codes and colour matrices (one per dataset).
        uncalibrated: (dataset_count,) bool, datasets whose colour matrix is learned in the warm-up.
    """

    def __init__(
        self,
        preset: Stage1Preset,
        template_vertices: torch.Tensor,
        binding: TexelBinding,
        subject_count: int,
        dataset_count: int,
        uncalibrated: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        template_vertices, self.spacing = bind_template(preset, template_vertices, binding)
        self.preset = preset
        self.binding = binding
        self.identity_codes = nn.Parameter(torch.randn(subject_count, preset.z_id_dim) * CODE_INIT_STD)
        self.lighting_codes = nn.Parameter(torch.randn(dataset_count, preset.z_l_dim) * CODE_INIT_STD)
        self.colour_matrices = nn.Parameter(torch.eye(3).repeat(dataset_count, 1, 1))
        flags = torch.zeros(dataset_count, dtype=torch.bool) if uncalibrated is None else uncalibrated.bool()
        self.register_buffer("uncalibrated", flags.clone())
        self.mesh_decoder = MeshDecoder(preset.z_id_dim, template_vertices, preset.mesh_hidden)
        self.geometry_decoder = ConvUVDecoder(
            preset.z_id_dim,
            GEOMETRY_CHANNELS,
            preset.uv_size,
            preset.start_channels,
            preset.min_channels,
            output_bias=geometry_output_bias(),
        )
        self.colour_decoder = ConvUVDecoder(
            preset.z_id_dim + preset.z_l_dim,
            COLOUR_CHANNELS,
            preset.uv_size,
            preset.start_channels,
            preset.min_channels,
            output_bias=colour_output_bias(),
        )
        # How the conv decoders run (set by a trainer; not part of the weights), see networks.precision.
        self.precision = "fp32"
        self.checkpoint_maps = False

    @property
    def gaussian_count(self) -> int:
        return self.binding.count

    def lighting_code(self, dataset_index: torch.Tensor, use_lighting: bool) -> torch.Tensor:
        """(B,) dataset indices -> (B, z_l) codes, zeros when the lighting code is switched off."""
        codes = self.lighting_codes[dataset_index]
        return codes if use_lighting else torch.zeros_like(codes)

    def forward(
        self,
        subject_index: torch.Tensor,
        lighting_index: torch.Tensor,
        use_lighting: bool = True,
    ) -> tuple[torch.Tensor, Gaussians]:
        """Decode subjects under datasets' lighting codes.

        Args:
            subject_index: (B,) int64 identity rows.
            lighting_index: (B,) int64 dataset whose lighting code colours each sample.
            use_lighting: False during the colour warm-up (z_l = 0).
        Returns:
            vertices (B, V, 3) decoded mesh and the Gaussians (N per sample).
        """
        z_id = self.identity_codes[subject_index]
        return self.decode(z_id, self.lighting_code(lighting_index, use_lighting))

    def decode(self, z_id: torch.Tensor, z_l: torch.Tensor) -> tuple[torch.Tensor, Gaussians]:
        """Decode explicit codes: z_id (B, D_id), z_l (B, D_l) -> vertices (B, V, 3) and the Gaussians."""
        vertices = self.mesh_decoder(z_id)
        how = {"precision": self.precision, "checkpointed": self.checkpoint_maps}
        geometry_maps = run_maps(self.geometry_decoder, z_id, **how)
        colour_maps = run_maps(self.colour_decoder, torch.cat([z_id, z_l], dim=1), **how)
        return vertices, assemble_gaussians(geometry_maps, colour_maps, vertices, self.binding, self.spacing)

    def dataset_colour(self, images: torch.Tensor, dataset_index: torch.Tensor) -> torch.Tensor:
        """Map rendered shared-space colour into each sample's dataset colour (warm-up only).

        images (B, 3, H, W), dataset_index (B,) -> (B, 3, H, W); identity for calibrated datasets.
        """
        eye = torch.eye(3, dtype=images.dtype, device=images.device)
        flags = self.uncalibrated[dataset_index].view(-1, 1, 1)
        matrices = torch.where(flags, self.colour_matrices[dataset_index], eye)
        return torch.einsum("bij,bjhw->bihw", matrices, images)
