"""A rough estimate of stage-1 training memory, printed before a run starts.

It counts what scales with the preset: parameters with their gradients and Adam moments, decoder
feature maps kept for the backward pass, the per-sample Gaussian tensors, and the rasterizer's image
and per-Gaussian buffers. Framework overhead (a few hundred MB) is not included.
"""

from __future__ import annotations

from relightanyone.model.networks.decoders import START_RESOLUTION, upsampling_channels
from relightanyone.model.networks.gaussians import COLOUR_CHANNELS, GEOMETRY_CHANNELS
from relightanyone.model.networks.presets import Stage1Preset

FLOAT_BYTES = 4
# Floats per Gaussian alive during a training step: raw maps, activated parameters, covariance,
# projection (means2d, conic, depth, radius) and their gradients.
FLOATS_PER_GAUSSIAN = 2 * (GEOMETRY_CHANNELS + COLOUR_CHANNELS + 3 + 4 + 3 + 1 + 3 + 3 + 9 + 8)
# Floats per image pixel in the rasterizer: colour, alpha, depth, transmittance and gradients, plus a
# bounded compositing chunk (the CPU compositor checkpoints chunks of 2^19 pixel-list entries).
FLOATS_PER_PIXEL = 2 * (COLOUR_CHANNELS + 3 + 8)
COMPOSITING_CHUNK_BYTES = (1 << 19) * 16 * FLOAT_BYTES


def decoder_activation_floats(preset: Stage1Preset) -> int:
    """Floats of one sample's feature maps in the two conv decoders (kept for backward)."""
    channels = upsampling_channels(preset.uv_size, preset.start_channels, preset.min_channels)
    total = 0
    for level, count in enumerate(channels):
        side = START_RESOLUTION * 2**level
        total += 2 * count * side * side  # pre- and post-activation
    total += (GEOMETRY_CHANNELS + COLOUR_CHANNELS) * preset.uv_size**2
    return 2 * total


def estimate_training_memory(
    preset: Stage1Preset, parameter_count: int, gaussian_count: int
) -> dict[str, int]:
    """Bytes by component for one training process; ``total`` sums them."""
    estimate = {
        "parameters": parameter_count * FLOAT_BYTES,
        "gradients": parameter_count * FLOAT_BYTES,
        "optimizer_state": 2 * parameter_count * FLOAT_BYTES,
        "decoder_activations": preset.batch_size * decoder_activation_floats(preset) * FLOAT_BYTES,
        "gaussians": preset.batch_size * gaussian_count * FLOATS_PER_GAUSSIAN * FLOAT_BYTES,
        "rasterizer": preset.batch_size * preset.crop_size**2 * FLOATS_PER_PIXEL * FLOAT_BYTES
        + COMPOSITING_CHUNK_BYTES,
    }
    estimate["total"] = sum(estimate.values())
    return estimate


def format_memory(estimate: dict[str, int]) -> str:
    """One line per component, in MiB."""
    lines = [f"  {name:<20} {value / 2**20:10.1f} MiB" for name, value in estimate.items()]
    return "estimated training memory per process:\n" + "\n".join(lines)
