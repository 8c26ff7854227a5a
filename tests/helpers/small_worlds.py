"""Synthetic worlds cut down for the ingest tests: the tiny preset with fewer subjects, cameras and pixels,
so that a world renders in seconds while keeping the tiny preset's layouts, conventions and faults."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from relightanyone.synth.presets import PRESETS, Preset
from relightanyone.synth.world import generate_world

# What every reduced world changes: a coarse template and texture, few answer lights, no environment maps.
REDUCED_DETAIL = dict(template_segments=16, texture_size=16, answer_lights=4, envmap_count=0)


def reduced_preset(**changes) -> Preset:
    """The tiny preset with :data:`REDUCED_DETAIL`, then ``changes`` (dataset sizes ``d1=DatasetSize(...)``,
    or other detail)."""
    return dataclasses.replace(PRESETS["tiny"], **{**REDUCED_DETAIL, **changes})


def make_world(folder: Path, preset: Preset, seed: int, datasets: tuple[str, ...]) -> Path:
    """Generate ``datasets`` of ``preset`` into ``folder/world`` (no progress bars); returns that folder."""
    out = folder / "world"
    generate_world(out, preset, seed=seed, datasets=datasets, progress=False)
    return out
