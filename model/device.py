"""The torch device a command runs on, from its ``--device`` value."""

from __future__ import annotations

import os

import torch

from relightanyone.errors import InputError


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when this machine has it, else the CPU; any other name must be a torch device
    (``cpu``, ``cuda``, ``cuda:1``, ...) that is available here."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as error:
        raise InputError(f"--device {name!r} is not a torch device ({error})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device {name}: CUDA is not available on this machine; use --device cpu")
    return device


def loader_workers(device: torch.device, requested: int | None = None) -> int:
    """Worker processes of a trainer's batch loader: ``requested``, or by default none on the CPU (the
    training step already uses every core; batches are made in the loop) and up to four on a GPU."""
    if requested is not None:
        if requested < 0:
            raise InputError(f"--loader-workers must be >= 0, got {requested}")
        return requested
    return min(4, max((os.cpu_count() or 1) // 2, 1)) if device.type == "cuda" else 0
