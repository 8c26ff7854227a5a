"""The single-stage baseline (paper §4.3): stage 1 with D_c replaced by relightable decoders.

The identity codes, ``D_mesh`` and ``D_g`` are those of stage 1. Instead of a full-on colour, two conv
decoders predict the RGCA reflectance directly:

* from z_id: albedo ρ, diffuse SH transfer d, roughness σ (the view-independent map);
* from [z_id, view direction]: visibility v and normal residual δn (the view-dependent map).

The channel layouts and activations are the stage-2 network's (:mod:`relightanyone.model.networks.reflectance`), so
both train through the same trainer and the same shading. The baseline is trained from scratch on the
OLAT dataset alone; it has no lighting code, because that dataset has one lighting.
"""

from __future__ import annotations

import torch
from torch import nn

from relightanyone.model.networks.decoders import ConvUVDecoder, MeshDecoder
from relightanyone.model.networks.gaussians import (
    GEOMETRY_CHANNELS,
    Gaussians,
    TexelBinding,
    assemble_gaussians,
    bind_template,
    gather_texels,
    geometry_output_bias,
)
from relightanyone.model.networks.precision import run_maps
from relightanyone.model.networks.presets import Stage1Preset
from relightanyone.model.networks.reflectance import (
    VIEW_DEPENDENT_CHANNELS,
    RelightParams,
    activate_relight_params,
    view_dependent_output_bias,
    view_independent_channels,
    view_independent_output_bias,
)
from relightanyone.model.networks.stage1 import CODE_INIT_STD
from relightanyone.model.networks.stage2 import VIEW_CHANNELS, head_frame, texel_mesh_normals, view_directions


class SingleStageModel(nn.Module):
    """Identity codes to geometry and reflectance in one network.

    Args:
        preset: stage-1 sizes (UV size, z_id, decoder widths).
        sh_order: order of the diffuse SH transfer.
        template_vertices: (V, 3) template mesh, canonical metres.
        binding: valid UV texels of the template (``uv_size`` must match the preset).
        subject_count: number of identity codes.
    """

    def __init__(
        self,
        preset: Stage1Preset,
        sh_order: int,
        template_vertices: torch.Tensor,
        binding: TexelBinding,
        subject_count: int,
    ) -> None:
        super().__init__()
        template_vertices, self.spacing = bind_template(preset, template_vertices, binding)
        self.preset = preset
        self.sh_order = sh_order
        self.binding = binding
        centre, _ = head_frame(template_vertices)
        self.register_buffer("head_centre", centre)
        self.register_buffer("albedo_scale", torch.ones(3))  # see Stage2Model: set by the trainer
        self.identity_codes = nn.Parameter(torch.randn(subject_count, preset.z_id_dim) * CODE_INIT_STD)
        self.mesh_decoder = MeshDecoder(preset.z_id_dim, template_vertices, preset.mesh_hidden)
        sizes = (preset.uv_size, preset.start_channels, preset.min_channels)
        self.geometry_decoder = ConvUVDecoder(
            preset.z_id_dim, GEOMETRY_CHANNELS, *sizes, output_bias=geometry_output_bias()
        )
        self.reflectance_decoder = ConvUVDecoder(
            preset.z_id_dim,
            view_independent_channels(sh_order),
            *sizes,
            output_bias=view_independent_output_bias(sh_order),
        )
        self.view_decoder = ConvUVDecoder(
            preset.z_id_dim + VIEW_CHANNELS,
            VIEW_DEPENDENT_CHANNELS,
            *sizes,
            output_bias=view_dependent_output_bias(),
        )
        # How the conv decoders run (set by a trainer; not part of the weights), see networks.precision.
        self.precision = "fp32"
        self.checkpoint_maps = False

    @property
    def gaussian_count(self) -> int:
        return self.binding.count

    def forward(
        self, subject_index: torch.Tensor, camera_positions: torch.Tensor
    ) -> tuple[torch.Tensor, Gaussians, RelightParams]:
        """Decode subjects seen from cameras.

        Args:
            subject_index: (B,) int64 identity rows.
            camera_positions: (B, 3) camera centres (canonical metres).
        Returns:
            vertices (B, V, 3), the Gaussians (N per sample; their ``colours`` hold the albedo until relit)
            and the reflectance.
        """
        z_id = self.identity_codes[subject_index]
        vertices = self.mesh_decoder(z_id)
        how = {"precision": self.precision, "checkpointed": self.checkpoint_maps}
        geometry_maps = run_maps(self.geometry_decoder, z_id, **how)
        reflectance_maps = run_maps(self.reflectance_decoder, z_id, **how)
        view = view_directions(camera_positions, self.head_centre)
        view_maps = run_maps(self.view_decoder, torch.cat([z_id, view], dim=1), **how)
        params = activate_relight_params(
            gather_texels(reflectance_maps, self.binding),
            gather_texels(view_maps, self.binding),
            texel_mesh_normals(vertices, self.binding),
            self.sh_order,
            self.albedo_scale,
        )
        albedo_maps = (
            torch.nn.functional.softplus(reflectance_maps[:, 0:3]) * self.albedo_scale[:, None, None]
        )
        gaussians = assemble_gaussians(geometry_maps, albedo_maps, vertices, self.binding, self.spacing)
        return vertices, gaussians, params
