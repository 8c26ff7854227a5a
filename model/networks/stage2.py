"""Stage 2 (paper §3.2): a UNet from full-on Gaussian colours to relightable RGCA reflectance.

Input, in UV space (B, 6, S, S): the full-on colour of every Gaussian from the frozen stage-1 model
(decoded with the OLAT dataset's lighting code) and its position, normalized about the head centre;
invalid texels are zero. A shared encoder E goes down to an 8×8 bottleneck, keeping one skip per
resolution. Two decoders go back up with those skips:

* ``D_ci`` (view-independent): albedo ρ, diffuse SH transfer d, roughness σ. ρ is predicted as a positive
  factor on the Gaussian's own full-on colour in albedo units (an input-to-output skip), so it follows
  the subject it is given; predicted directly, a network trained on a few OLAT subjects learns one
  albedo for everyone and ignores its colour input;
* ``D_cv`` (view-dependent): the bottleneck concatenated with the view direction (camera position to head
  centre, tiled over the 8×8 map), to visibility v and normal residual δn.

Layer pattern: 3×3 convolutions and LeakyReLU(0.2) as the stage-1 decoders; stride-2 4×4 convolutions
down, stride-2 4×4 transposed convolutions up. Output activations live in
:mod:`relightanyone.model.networks.reflectance`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from relightanyone.errors import InputError
from relightanyone.model.networks.decoders import LEAKY_SLOPE, START_RESOLUTION
from relightanyone.model.networks.gaussians import TexelBinding, gather_texels
from relightanyone.model.networks.precision import run_maps
from relightanyone.model.networks.reflectance import (
    INITIAL_ALBEDO,
    VIEW_DEPENDENT_CHANNELS,
    RelightParams,
    activate_relight_params,
    view_dependent_output_bias,
    view_independent_channels,
    view_independent_output_bias,
)
from relightanyone.render.mesh import vertex_normals

INPUT_CHANNELS = 6  # full-on colour (3) + normalized position (3)
VIEW_CHANNELS = 3


def level_channels(uv_size: int, base_channels: int, max_channels: int) -> list[int]:
    """Channels of the UNet levels S, S/2, ..., 8 (the last entry is the bottleneck).

    Doubles per level down from ``base_channels`` and never exceeds ``max_channels``.
    """
    if uv_size < START_RESOLUTION or uv_size & (uv_size - 1):
        raise ValueError(f"uv_size must be a power of two >= {START_RESOLUTION}, got {uv_size}")
    levels = int(math.log2(uv_size // START_RESOLUTION)) + 1
    return [min(base_channels * 2**level, max_channels) for level in range(levels)]


def _conv_block(in_channels: int, out_channels: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, padding=1), nn.LeakyReLU(LEAKY_SLOPE))


class UNetEncoder(nn.Module):
    """E: (B, C_in, S, S) -> features at S, S/2, ..., 8 (the last one is the bottleneck)."""

    def __init__(self, in_channels: int, channels: list[int]) -> None:
        super().__init__()
        self.stem = _conv_block(in_channels, channels[0])
        self.down = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(c_in, c_out, 4, stride=2, padding=1),
                nn.LeakyReLU(LEAKY_SLOPE),
                _conv_block(c_out, c_out),
            )
            for c_in, c_out in zip(channels[:-1], channels[1:], strict=True)
        )

    def forward(self, inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        features = [self.stem(inputs)]
        for layer in self.down:
            features.append(layer(features[-1]))
        return tuple(features)


class UNetDecoder(nn.Module):
    """Bottleneck (B, C_b + extra, 8, 8) and skips -> (B, out_channels, S, S).

    ``extra_channels`` are concatenated to the bottleneck by the caller (the view direction of D_cv). The
    last 1×1 layer starts with small weights and ``output_bias``, so the untrained decoder outputs roughly
    that bias everywhere.
    """

    def __init__(
        self, channels: list[int], out_channels: int, output_bias: torch.Tensor, extra_channels: int = 0
    ) -> None:
        super().__init__()
        self.bottleneck = _conv_block(channels[-1] + extra_channels, channels[-1])
        self.up = nn.ModuleList()
        self.fuse = nn.ModuleList()
        for c_in, c_skip in zip(reversed(channels[1:]), reversed(channels[:-1]), strict=True):
            self.up.append(
                nn.Sequential(
                    nn.ConvTranspose2d(c_in, c_skip, 4, stride=2, padding=1), nn.LeakyReLU(LEAKY_SLOPE)
                )
            )
            self.fuse.append(_conv_block(2 * c_skip, c_skip))
        self.output = nn.Conv2d(channels[0], out_channels, 1)
        nn.init.normal_(self.output.weight, std=1e-3)
        with torch.no_grad():
            self.output.bias.copy_(output_bias)

    def forward(self, bottleneck: torch.Tensor, *skips: torch.Tensor) -> torch.Tensor:
        """bottleneck (B, C_b + extra, 8, 8); skips: encoder features at S, ..., 16 -> (B, out, S, S)."""
        x = self.bottleneck(bottleneck)
        for up, fuse, skip in zip(self.up, self.fuse, reversed(skips), strict=True):
            x = fuse(torch.cat([up(x), skip], dim=1))
        return self.output(x)


class RelightingUNet(nn.Module):
    """E with D_ci and D_cv: inputs (B, 6, S, S), view directions (B, 3) ->
    view-independent maps (B, 3 + 3K + 1, S, S) and view-dependent maps (B, 4, S, S), raw."""

    def __init__(self, uv_size: int, sh_order: int, base_channels: int, max_channels: int) -> None:
        super().__init__()
        channels = level_channels(uv_size, base_channels, max_channels)
        self.uv_size = uv_size
        self.sh_order = sh_order
        self.encoder = UNetEncoder(INPUT_CHANNELS, channels)
        self.view_independent = UNetDecoder(
            channels, view_independent_channels(sh_order), view_independent_output_bias(sh_order)
        )
        self.view_dependent = UNetDecoder(
            channels, VIEW_DEPENDENT_CHANNELS, view_dependent_output_bias(), extra_channels=VIEW_CHANNELS
        )

    def forward(
        self,
        inputs: torch.Tensor,
        view_dirs: torch.Tensor,
        precision: str = "fp32",
        checkpointed: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``precision`` and ``checkpointed``: how the encoder and each decoder run
        (:func:`~relightanyone.model.networks.precision.run_maps`; outputs are float32 either way)."""
        if inputs.shape[1:] != (INPUT_CHANNELS, self.uv_size, self.uv_size):
            raise ValueError(
                f"stage-2 input must be (B, {INPUT_CHANNELS}, {self.uv_size}, {self.uv_size}), got {tuple(inputs.shape)}"
            )
        how = {"precision": precision, "checkpointed": checkpointed}
        features = run_maps(self.encoder, inputs, **how)
        bottleneck, skips = features[-1], list(features[:-1])
        tiled_view = view_dirs[:, :, None, None].expand(-1, -1, *bottleneck.shape[2:])
        return (
            run_maps(self.view_independent, bottleneck, *skips, **how),
            run_maps(self.view_dependent, torch.cat([bottleneck, tiled_view], dim=1), *skips, **how),
        )


def scatter_texels(values: torch.Tensor, binding: TexelBinding) -> torch.Tensor:
    """Per-Gaussian values into UV maps, zero at invalid texels: (B, N, C) -> (B, C, S, S)."""
    batch, _, channels = values.shape
    size = binding.uv_size
    flat = values.new_zeros(batch, channels, size * size)
    flat = flat.index_copy(2, binding.valid_index.to(values.device), values.transpose(1, 2))
    return flat.view(batch, channels, size, size)


def texel_mesh_normals(vertices: torch.Tensor, binding: TexelBinding) -> torch.Tensor:
    """Smooth mesh normals n̂ at every valid texel: vertices (B, V, 3) -> unit (B, N, 3)."""

    device = vertices.device
    normals = vertex_normals(vertices, binding.faces.to(device))
    corners = binding.faces.to(device)[binding.texel_faces.to(device)]  # (N, 3) vertex ids
    weights = binding.texel_barycentrics.to(device, normals.dtype)
    return F.normalize((normals[:, corners] * weights[None, :, :, None]).sum(dim=2), dim=-1)


def head_frame(template_vertices: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Head centre (3,) (the template's bounding-box centre) and radius (farthest vertex from it), metres."""
    template_vertices = torch.as_tensor(template_vertices, dtype=torch.float32)
    centre = 0.5 * (template_vertices.min(dim=0).values + template_vertices.max(dim=0).values)
    radius = float((template_vertices - centre).norm(dim=-1).max())
    if radius <= 0:
        raise InputError("the template mesh is a single point; cannot define a head centre and radius")
    return centre, radius


def view_directions(camera_positions: torch.Tensor, head_centre: torch.Tensor) -> torch.Tensor:
    """Unit directions from each camera to the head centre: (B, 3), (3,) -> (B, 3)."""
    return F.normalize(head_centre - camera_positions, dim=-1)


class Stage2Model(nn.Module):
    """The stage-2 network around a frozen stage-1 model's Gaussians.

    Args:
        binding: valid UV texels of the stage-1 model.
        head_centre: (3,) canonical metres; radius: metres, to normalize positions into about [-1, 1].
        sh_order, base_channels, max_channels: see :class:`relightanyone.model.networks.presets.Stage2Preset`.
    """

    def __init__(
        self,
        binding: TexelBinding,
        head_centre: torch.Tensor,
        radius: float,
        sh_order: int,
        base_channels: int,
        max_channels: int,
    ) -> None:
        super().__init__()
        self.binding = binding
        self.sh_order = sh_order
        self.radius = float(radius)
        self.register_buffer("head_centre", torch.as_tensor(head_centre, dtype=torch.float32).clone())
        # Image units per unit of albedo x rig light: set by the trainer from the data, saved with the weights.
        self.register_buffer("albedo_scale", torch.ones(3))
        # Albedo per unit of full-on colour (one over the full-on rig's mean diffuse light): D_ci predicts a
        # positive factor on colour x albedo_per_colour, so the albedo follows the colours it is given.
        self.register_buffer("albedo_per_colour", torch.ones(3))
        self.unet = RelightingUNet(binding.uv_size, sh_order, base_channels, max_channels)
        # How the UNet runs (set by a trainer; not part of the weights), see networks.precision.
        self.precision = "fp32"
        self.checkpoint_maps = False

    def input_maps(self, colours: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """E's input: full-on colours (B, N, 3) and positions (B, N, 3) -> (B, 6, S, S)."""
        normalized = (positions - self.head_centre) / self.radius
        return scatter_texels(torch.cat([colours, normalized], dim=-1), self.binding)

    def forward(
        self,
        colours: torch.Tensor,
        positions: torch.Tensor,
        mesh_normals: torch.Tensor,
        camera_positions: torch.Tensor,
    ) -> RelightParams:
        """Reflectance of every Gaussian.

        Args:
            colours: (B, N, 3) full-on colours from stage 1 (z_l of the OLAT dataset).
            positions: (B, N, 3) Gaussian centres.
            mesh_normals: (B, N, 3) unit mesh normals n̂ (:func:`texel_mesh_normals`).
            camera_positions: (B, 3).
        """
        view_independent, view_dependent = self.unet(
            self.input_maps(colours, positions),
            view_directions(camera_positions, self.head_centre),
            self.precision,
            self.checkpoint_maps,
        )
        # ρ = colour · albedo_per_colour · softplus(raw) / softplus(bias): the untrained decoder returns the
        # input texture in albedo units, and training learns the (mostly shading) factor away from it.
        texture_albedo = colours.clamp(min=0.0) * self.albedo_per_colour / INITIAL_ALBEDO
        return activate_relight_params(
            gather_texels(view_independent, self.binding),
            gather_texels(view_dependent, self.binding),
            mesh_normals,
            self.sh_order,
            texture_albedo,
        )
