"""Stage-1 decoders: identity/lighting codes to a mesh and to UV maps of Gaussian parameters.

The conv decoders follow the RGCA primitive decoder: a linear map to an 8×8 feature map, then one
stride-2 transposed convolution per doubling of resolution (kernel 4, padding 1) with LeakyReLU(0.2)
between layers, until the UV size is reached. The last layer has no activation; the activations that
give each parameter its range live in :mod:`relightanyone.model.networks.gaussians`.
"""

from __future__ import annotations

import math

import torch
from torch import nn

LEAKY_SLOPE = 0.2
START_RESOLUTION = 8


def upsampling_channels(uv_size: int, start_channels: int, min_channels: int) -> list[int]:
    """Channels of the feature maps at 8, 16, ..., ``uv_size`` / 2 (the inputs of each upsampling layer).

    Halves the channel count after every layer but the first (RGCA keeps 256 at 16²) and never goes
    below ``min_channels``.
    """
    layers = int(math.log2(uv_size // START_RESOLUTION))
    if layers == 0:
        return []
    channels = [start_channels]
    for index in range(1, layers):
        previous = channels[-1]
        channels.append(previous if index == 1 else max(previous // 2, min_channels))
    return channels


class ConvUVDecoder(nn.Module):
    """Code (B, D) -> UV map (B, out_channels, S, S).

    Args:
        code_dim: D, length of the input code.
        out_channels: channels of the output map.
        uv_size: S, a power of two >= 8.
        start_channels: channels of the first 8×8 map.
        min_channels: lower bound of the channel count while upsampling.
        output_bias: optional (out_channels,) initial value of the output; the last layer starts with
            small weights so the untrained decoder outputs roughly this everywhere.
    """

    def __init__(
        self,
        code_dim: int,
        out_channels: int,
        uv_size: int,
        start_channels: int,
        min_channels: int,
        output_bias: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        if uv_size < START_RESOLUTION or uv_size & (uv_size - 1):
            raise ValueError(f"uv_size must be a power of two >= {START_RESOLUTION}, got {uv_size}")
        self.uv_size = uv_size
        self.start_channels = start_channels
        self.to_grid = nn.Linear(code_dim, start_channels * START_RESOLUTION**2)
        channels = upsampling_channels(uv_size, start_channels, min_channels)
        layers: list[nn.Module] = []
        for index, in_channels in enumerate(channels):
            last = index == len(channels) - 1
            next_channels = out_channels if last else channels[index + 1]
            layers.append(nn.ConvTranspose2d(in_channels, next_channels, kernel_size=4, stride=2, padding=1))
            if not last:
                layers.append(nn.LeakyReLU(LEAKY_SLOPE))
        if not channels:  # uv_size == 8: the linear map already has the final resolution
            layers.append(nn.Conv2d(start_channels, out_channels, kernel_size=1))
        self.layers = nn.Sequential(*layers)
        output_layer = layers[-1]
        # Small last-layer weights: every texel starts near output_bias, a sane Gaussian.
        nn.init.normal_(output_layer.weight, std=1e-3)
        with torch.no_grad():
            output_layer.bias.zero_()
            if output_bias is not None:
                output_layer.bias.copy_(torch.as_tensor(output_bias, dtype=output_layer.bias.dtype))

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """code (B, D) -> (B, out_channels, S, S)."""
        grid = self.to_grid(code).view(code.shape[0], self.start_channels, START_RESOLUTION, START_RESOLUTION)
        return self.layers(nn.functional.leaky_relu(grid, LEAKY_SLOPE))


class MeshDecoder(nn.Module):
    """D_mesh: identity code (B, D) -> template-topology vertices (B, V, 3) in canonical metres.

    An MLP predicting per-vertex offsets from the template mesh; the last layer starts at zero so the
    untrained decoder returns the template itself.
    """

    def __init__(self, code_dim: int, template_vertices: torch.Tensor, hidden: int) -> None:
        super().__init__()
        template_vertices = torch.as_tensor(template_vertices, dtype=torch.float32)
        if template_vertices.ndim != 2 or template_vertices.shape[1] != 3:
            raise ValueError(f"template_vertices must be (V, 3), got {tuple(template_vertices.shape)}")
        self.register_buffer("template_vertices", template_vertices.clone())
        self.mlp = nn.Sequential(
            nn.Linear(code_dim, hidden),
            nn.LeakyReLU(LEAKY_SLOPE),
            nn.Linear(hidden, template_vertices.numel()),
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """code (B, D) -> vertices (B, V, 3)."""
        offsets = self.mlp(code).view(code.shape[0], -1, 3)
        return self.template_vertices.unsqueeze(0) + offsets
