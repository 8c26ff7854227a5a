"""Atomic training checkpoints that resume bit-exactly and cannot carry code.

A checkpoint holds the model and optimizer state, the iteration it was taken after (the position of the
stateless sampler, see :mod:`relightanyone.model.train.sampling`) and the Python, NumPy and torch random
states. It is written to a temporary file in the same folder, flushed to disk and renamed over the
previous one, so a process killed at any moment leaves either the old or the new checkpoint, never a
torn one.

A checkpoint file is data: it is read with ``torch.load(weights_only=True)``, which builds only tensors
and plain values (dicts, lists, tuples, strings, numbers) and refuses any other Python object, so a
crafted file cannot run code when it is opened. Every random state is stored in those plain types
(NumPy's as a dict of numbers, see :func:`capture_rng_state`). Files written before that stored NumPy's
state as a pickled ``ndarray``; :func:`load_checkpoint` reads that one array through stand-ins that build
nothing but a little-endian ``uint32`` vector (no NumPy code runs), and converts the state.
"""

from __future__ import annotations

import os
import pickle
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.os_errors import naming_file

REQUIRED_FIELDS = ("iteration", "model", "optimizer", "rng", "preset", "subjects", "seed")
NUMPY_BIT_GENERATOR = "MT19937"


def capture_rng_state() -> dict[str, Any]:
    """Random states of Python, NumPy (global generator) and torch (CPU, and CUDA when present), in plain
    types: NumPy's ``(name, key (624,) uint32, pos, has_gauss, cached_gaussian)`` becomes a dict."""
    name, key, pos, has_gauss, cached_gaussian = np.random.get_state()
    state = {
        "python": random.getstate(),
        "numpy": {
            "bit_generator": str(name),
            "key": [int(k) for k in key],
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached_gaussian),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state`."""
    numpy_state = state["numpy"]
    random.setstate(state["python"])
    np.random.set_state(
        (
            numpy_state["bit_generator"],
            np.asarray(numpy_state["key"], dtype=np.uint32),
            numpy_state["pos"],
            numpy_state["has_gauss"],
            numpy_state["cached_gaussian"],
        )
    )
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` with ``torch.save`` atomically (temporary file, fsync, rename, fsync folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with naming_file(temporary), open(temporary, "wb") as handle:  # a failed write names no file
        torch.save(payload, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


class _LegacyUint32Dtype:
    """Stand-in for ``numpy.dtype`` in older checkpoints: accepts only a little-endian ``uint32``."""

    def __init__(self, code: str, align: bool = False, copy: bool = True):
        if code != "u4":
            raise pickle.UnpicklingError(f"numpy dtype {code!r} (only the uint32 random state is read)")

    def __setstate__(self, state: tuple) -> None:
        if not isinstance(state, tuple) or len(state) < 2 or state[1] not in ("<", "="):
            raise pickle.UnpicklingError("numpy dtype state other than a little-endian uint32")


class _LegacyUint32Array:
    """Stand-in for ``numpy.ndarray`` in older checkpoints: raw little-endian ``uint32`` bytes only."""

    values: list[int]

    def __setstate__(self, state: tuple) -> None:
        if not (isinstance(state, tuple) and len(state) == 5):
            raise pickle.UnpicklingError("numpy array state of an unknown form")
        _, shape, dtype, fortran_order, raw = state
        if not isinstance(dtype, _LegacyUint32Dtype) or not isinstance(raw, bytes) or fortran_order:
            raise pickle.UnpicklingError("numpy array other than a uint32 vector")
        if not (isinstance(shape, tuple) and len(shape) == 1 and len(raw) == 4 * shape[0]):
            raise pickle.UnpicklingError(f"numpy array of shape {shape!r} with {len(raw)} bytes")
        self.values = np.frombuffer(raw, dtype="<u4").tolist()


def _legacy_reconstruct(cls: type, shape: tuple, typecode: bytes) -> _LegacyUint32Array:
    """Stand-in for ``numpy.core.multiarray._reconstruct``: an empty array filled by ``__setstate__``."""
    if cls is not _LegacyUint32Array:
        raise pickle.UnpicklingError(f"numpy array of class {cls!r}")
    return _LegacyUint32Array()


# The names older checkpoints give the pieces of one pickled ndarray (NumPy 1 and 2 module paths).
_LEGACY_NUMPY_STANDINS = [
    (_legacy_reconstruct, "numpy.core.multiarray._reconstruct"),
    (_legacy_reconstruct, "numpy._core.multiarray._reconstruct"),
    (_LegacyUint32Array, "numpy.ndarray"),
    (_LegacyUint32Dtype, "numpy.dtype"),
]


def _plain_numpy_state(state: Any) -> dict[str, Any]:
    """NumPy's random state as :func:`capture_rng_state` stores it, from either form a file may hold."""
    if isinstance(state, dict):
        return state
    name, key, pos, has_gauss, cached_gaussian = state
    return {
        "bit_generator": str(name),
        "key": key.values if isinstance(key, _LegacyUint32Array) else list(key),
        "pos": int(pos),
        "has_gauss": int(has_gauss),
        "cached_gaussian": float(cached_gaussian),
    }


def _refusal_detail(error: pickle.UnpicklingError) -> str:
    """What the weights-only unpickler refused, from its message (the object a file asks for, or the
    first line of the complaint), without torch's advice on how to load the file anyway."""
    text = str(error)
    asked = re.search(r"GLOBAL ([\w.]+)", text)
    if asked:
        return f"it asks for {asked.group(1)}"
    complaint = re.search(r"WeightsUnpickler error:\s*(.+)", text)
    return complaint.group(1).strip() if complaint else "content other than tensors and plain values"


def read_plain_torch_file(path: Path, what: str, remedy: str) -> Any:
    """``torch.load(path, weights_only=True)``: only tensors and plain values are built (and the NumPy
    random state of older checkpoints, through the stand-ins above). Any failure is a ``ValueError`` of
    one line naming the file, the ``what`` it should have been and the ``remedy``."""
    try:
        with torch.serialization.safe_globals(_LEGACY_NUMPY_STANDINS):
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        raise InputError(
            f"{path}: refused: a {what} holds only tensors and plain values, and this file does not "
            f"({_refusal_detail(error)}); loading it could run code, so it was not loaded: {remedy}"
        ) from None
    except (RuntimeError, OSError) as error:
        # torch's messages run on with advice; the first sentence says what is wrong.
        first = re.split(r"(?<=\.)\s", str(error).strip(), maxsplit=1)[0] or type(error).__name__
        raise InputError(f"{path}: unreadable {what} ({first}); {remedy}") from None
    except Exception:  # on bytes that are no pickle at all the unpickler fails with KeyError, EOFError, ...
        raise InputError(f"{path}: not a {what} (not a torch file); {remedy}") from None


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (or by an older version of it, whose NumPy
    random state is converted); only tensors and plain values are built. Errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no checkpoint; train first (relightanyone train stage1 ... --out RUN)"
        )
    payload = read_plain_torch_file(path, "training checkpoint", "delete it and train again")
    missing = [f for f in REQUIRED_FIELDS if not isinstance(payload, dict) or f not in payload]
    if missing:
        raise InputError(
            f"{path}: not a training checkpoint (field {missing[0]!r} is missing); delete it and train again"
        )
    try:
        payload["rng"]["numpy"] = _plain_numpy_state(payload["rng"]["numpy"])
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"{path}: field 'rng' is not a random state ({error!r})") from None
    return payload
