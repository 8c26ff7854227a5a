"""Mixed precision and activation checkpointing of the convolutional UV-map networks.

Only the convolutions that make UV maps (the stage-1 decoders, the stage-2 UNet, the single-stage
decoders) may run in bfloat16: they hold nearly all of a step's activation memory and tolerate its 8-bit
mantissa. Everything per Gaussian (positions on the mesh, covariances, shading, the rasterizer) and every
loss stays float32: a position of 0.1 m in bfloat16 is off by up to 0.4 mm, more than a texel at 1024².
So the maps are made under :func:`map_autocast` and turned back into float32 as they leave it.

Checkpointing (``torch.utils.checkpoint``) drops a network's inner activations after the forward pass and
recomputes them in the backward pass: the same gradients, for about one more forward of that network.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext

import torch
from torch.utils.checkpoint import checkpoint

PRECISIONS = ("fp32", "bf16")


def check_precision(precision: str) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    return precision


def map_autocast(device: torch.device, precision: str) -> AbstractContextManager:
    """bfloat16 autocast on ``device`` when ``precision`` is ``bf16``; a no-op context for ``fp32`` and on
    the meta device (shapes only: memory estimates count its maps at bfloat16 size themselves)."""
    if check_precision(precision) == "fp32" or device.type == "meta":
        return nullcontext()
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16)


def run_maps(
    network: Callable[..., torch.Tensor | tuple[torch.Tensor, ...]],
    *inputs: torch.Tensor,
    precision: str = "fp32",
    checkpointed: bool = False,
):
    """``network(*inputs)`` under :func:`map_autocast`, checkpointed when asked; every output float32.

    The network returns one tensor or a tuple of them (UV maps (B, C, S, S)).
    """
    device = inputs[0].device

    def forward(*args: torch.Tensor):
        with map_autocast(device, precision):
            return network(*args)

    if checkpointed and torch.is_grad_enabled():
        outputs = checkpoint(forward, *inputs, use_reentrant=False)
    else:
        outputs = forward(*inputs)
    if isinstance(outputs, tuple):
        return tuple(output.float() for output in outputs)
    return outputs.float()
