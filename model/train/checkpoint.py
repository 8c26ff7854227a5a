"""Atomic training checkpoints that resume bit-exactly.

A checkpoint holds the model and optimizer state, the iteration it was taken after (the position of the
stateless sampler, see :mod:`relightanyone.model.train.sampling`) and the Python, NumPy and torch random
states. It is written to a temporary file in the same folder, flushed to disk and renamed over the
previous one, so a process killed at any moment leaves either the old or the new checkpoint, never a
torn one.
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relightanyone.errors import InputError


def capture_rng_state() -> dict[str, Any]:
    """Random states of Python, NumPy (global generator) and torch (CPU, and CUDA when present)."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state`."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` with ``torch.save`` atomically (temporary file, fsync, rename, fsync folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(temporary, "wb") as handle:
        torch.save(payload, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`; the error names the file when it is unreadable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no checkpoint; train first (relightanyone train stage1 ... --out RUN)"
        )
    try:
        # Checkpoints hold NumPy random states, which the weights-only unpickler refuses.
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # torch raises several unrelated types for a corrupt file
        raise InputError(f"{path}: unreadable checkpoint ({error}); delete it to start over") from error
