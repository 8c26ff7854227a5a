"""Where a dataset keeps its learned colour matrix: ``colour_alignment.json`` beside its manifest.

The colour warm-up learns a 3×3 per uncalibrated dataset (and one per camera of its rig) and writes them
into a view of that dataset (:mod:`relightanyone.format.dataset_view`); loaders read them and apply the
row's camera's matrix, ``aligned = M @ rgb``. The
document itself (format tag, version, convention, checks) is defined in :mod:`relightanyone.align.colour`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from relightanyone.align.colour import LearnedColour, colour_alignment_text, parse_colour_alignment
from relightanyone.format.schema import COLOUR_ALIGNMENT_NAME


def write_learned_colour_matrix(
    dataset_dir: str | os.PathLike,
    M: Any,
    info: Mapping[str, Any] | None = None,
    cameras: Mapping[str, Any] | None = None,
) -> Path:
    """Write the learned 3×3 ``M``, the per-camera ones (name -> 3×3) and free-form JSON ``info`` into
    ``dataset_dir`` atomically; returns the path written."""
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise FileNotFoundError(f"{dataset_dir}: dataset folder does not exist")
    text = colour_alignment_text(M, info, cameras)
    target = dataset_dir / COLOUR_ALIGNMENT_NAME
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, target)
    return target


def read_learned_colour(dataset_dir: str | os.PathLike) -> LearnedColour | None:
    """The learned alignment of ``dataset_dir`` (its matrix and per-camera matrices), or None when it has
    none."""
    path = Path(dataset_dir) / COLOUR_ALIGNMENT_NAME
    if not path.is_file():
        return None
    return parse_colour_alignment(path.read_bytes(), str(path))
