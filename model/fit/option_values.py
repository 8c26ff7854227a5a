"""Numbers given on the command line for relighting and export: positions, colours, point lights, exposure.

Pure Python (no torch), so the command line parses and checks them before anything heavy is imported.
Each parser raises ValueError with the value and the problem; the command line names the option.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def parse_floats(text: str, lengths: Sequence[int]) -> tuple[float, ...]:
    """``"x,y,z"`` -> floats; raises ValueError unless they are finite and their count is one of ``lengths``."""
    try:
        values = tuple(float(part) for part in text.replace(" ", "").split(",") if part != "")
    except ValueError:
        raise ValueError(f"{text!r}: not comma-separated numbers") from None
    if len(values) not in lengths or not all(math.isfinite(v) for v in values):
        counts = " or ".join(str(n) for n in lengths)
        raise ValueError(f"{text!r}: expected {counts} finite comma-separated numbers")
    return values


def parse_triple(text: str) -> tuple[float, ...]:
    """``"a,b,c"`` -> three finite numbers (a position in metres, or a linear RGB colour)."""
    return parse_floats(text, (3,))


def parse_point_light(spec: str) -> tuple[float, ...]:
    """``"x,y,z"`` or ``"x,y,z,r,g,b"`` -> its 3 or 6 numbers; raises ValueError for anything else or for a
    negative intensity."""
    values = parse_floats(spec, (3, 6))
    if len(values) == 6 and min(values[3:]) < 0:
        raise ValueError(f"{spec!r}: intensities r,g,b must be >= 0")
    return values


def parse_point_lights(specs: Sequence[str]) -> tuple[tuple[float, ...], ...]:
    """Every ``--point-light`` spec parsed (:func:`parse_point_light`)."""
    return tuple(parse_point_light(spec) for spec in specs)


def parse_exposure(text: str) -> float | None:
    """``"auto"`` -> None (auto exposure); a number of stops -> float; anything else raises ValueError."""
    if text.strip().lower() == "auto":
        return None
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{text!r}: give a number of stops (e.g. 0, -1.5) or 'auto'") from None
