"""Light sources: point lights (an OLAT rig, arbitrary lights) and directional lights.

Conventions (docs/conventions.md): positions in metres in canonical head space, intensities linear RGB.
A point light's ``intensity`` is radiant intensity: the irradiance it gives at distance ``r`` facing it is
``intensity / r**2`` (the shading functions apply this falloff unless told not to). A directional light's
``irradiance`` is what it gives on a surface facing it, so an environment-map texel becomes
``radiance * solid_angle``. Directions point from the subject towards the light.

An OLAT rig is the ordered list of its lights; "full-on" is all of them at once; padding lights (to batch
rigs of different sizes) have zero intensity and contribute nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from relightanyone.render.errors import FileFormatError


@dataclass(frozen=True)
class PointLights:
    """Point lights.

    Attributes:
        positions: ``(L, 3)`` metres, canonical head space.
        intensities: ``(L, 3)`` linear RGB radiant intensity.
    """

    positions: torch.Tensor
    intensities: torch.Tensor

    def __post_init__(self) -> None:
        _check_pair(self.positions, self.intensities, "positions", "intensities", "PointLights")

    def __len__(self) -> int:
        return self.positions.shape[0]

    def select(self, indices: Sequence[int] | torch.Tensor) -> PointLights:
        """The lights at ``indices`` (in that order)."""
        index = torch.as_tensor(indices, dtype=torch.long, device=self.positions.device).reshape(-1)
        if len(index) and (index.min() < 0 or index.max() >= len(self)):
            raise IndexError(f"light index out of range [0, {len(self)}): {index.tolist()}")
        return PointLights(self.positions[index], self.intensities[index])

    def olat(self, index: int) -> PointLights:
        """One-light-at-a-time pattern: only light ``index`` of the rig."""
        return self.select([index])

    def full_on(self) -> PointLights:
        """Every light of the rig at once (the rig itself)."""
        return self

    def scaled(self, factor: float | torch.Tensor) -> PointLights:
        """Intensities multiplied by ``factor`` (a scalar or an RGB ``(3,)`` gain)."""
        return PointLights(self.positions, self.intensities * factor)

    def transformed(self, matrix: torch.Tensor) -> PointLights:
        """Positions mapped by a 4x4 rigid/similarity transform (e.g. folding a head pose into the rig)."""
        matrix = torch.as_tensor(matrix, dtype=self.positions.dtype, device=self.positions.device)
        if matrix.shape != (4, 4):
            raise ValueError(f"transform must be 4x4, got {tuple(matrix.shape)}")
        return PointLights(self.positions @ matrix[:3, :3].T + matrix[:3, 3], self.intensities)

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None) -> PointLights:
        return PointLights(self.positions.to(device, dtype), self.intensities.to(device, dtype))


@dataclass(frozen=True)
class DirectionalLights:
    """Lights at infinity.

    Attributes:
        directions: ``(L, 3)`` unit vectors from the subject towards each light.
        irradiance: ``(L, 3)`` linear RGB irradiance on a surface facing the light.
    """

    directions: torch.Tensor
    irradiance: torch.Tensor

    def __post_init__(self) -> None:
        _check_pair(self.directions, self.irradiance, "directions", "irradiance", "DirectionalLights")

    def __len__(self) -> int:
        return self.directions.shape[0]

    def as_point_lights(self, distance_m: float) -> PointLights:
        """Point lights at ``distance_m`` that give the same irradiance at the origin (inverse-square)."""
        return PointLights(self.directions * distance_m, self.irradiance * distance_m**2)

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None) -> DirectionalLights:
        return DirectionalLights(self.directions.to(device, dtype), self.irradiance.to(device, dtype))


def olat_rig_from_table(table: Any, source: str = "lights table") -> PointLights:
    """Build an OLAT rig from a ``lights.arrow`` table.

    Args:
        table: a ``pyarrow.Table`` (or a mapping of column name -> sequence) with ``position_m``
            (list<float64>[3]) and ``intensity_rgb`` (list<float64>[3]); an optional ``index`` column orders
            the lights (it must be a permutation of ``0..L-1``).
        source: name used in error messages (e.g. the file path).

    Returns:
        :class:`PointLights` in rig order, float32.
    """
    columns = _columns(table)
    for name in ("position_m", "intensity_rgb"):
        if name not in columns:
            raise FileFormatError(f"{source}: missing column '{name}' (found {sorted(columns)})")
    positions = _vector_column(columns["position_m"], "position_m", source)
    intensities = _vector_column(columns["intensity_rgb"], "intensity_rgb", source)
    if len(positions) != len(intensities):
        raise FileFormatError(
            f"{source}: position_m has {len(positions)} rows but intensity_rgb has {len(intensities)}"
        )
    if (intensities < 0).any():
        raise FileFormatError(f"{source}: intensity_rgb has negative values")
    if "index" in columns:
        index = np.asarray(columns["index"], dtype=np.int64)
        if sorted(index.tolist()) != list(range(len(index))):
            raise FileFormatError(f"{source}: column 'index' must be a permutation of 0..{len(index) - 1}")
        order = np.argsort(index)
        positions, intensities = positions[order], intensities[order]
    return PointLights(
        torch.from_numpy(positions.astype(np.float32)), torch.from_numpy(intensities.astype(np.float32))
    )


def full_on_rig_from_table(table: Any, rig: PointLights, source: str = "lights table") -> PointLights:
    """The rig as lit in the full-on pattern: ``full_on_intensity_rgb`` where the table has it, else ``rig``.

    Light stages often shorten each light's exposure in the full-on frame (the synthetic FaceOLAT: 1/20 of
    its OLAT duration), so a full-on image is not the sum of the OLAT images; training and fitting on
    full-on frames must use these intensities. ``rig`` is :func:`olat_rig_from_table` of the same table.
    """
    columns = _columns(table)
    values = columns.get("full_on_intensity_rgb")
    if values is None or any(v is None for v in values):
        return rig
    intensities = _vector_column(values, "full_on_intensity_rgb", source)
    if "index" in columns:
        intensities = intensities[np.argsort(np.asarray(columns["index"], dtype=np.int64))]
    if (intensities < 0).any():
        raise FileFormatError(f"{source}: full_on_intensity_rgb has negative values")
    return PointLights(rig.positions, torch.from_numpy(intensities.astype(np.float32)))


def stack_padded(rigs: Sequence[PointLights]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batch rigs of different sizes; padding lights have zero intensity.

    Returns:
        positions ``(B, Lmax, 3)``, intensities ``(B, Lmax, 3)``, counts ``(B,)`` int64.
    """
    if not rigs:
        raise ValueError("stack_padded needs at least one rig")
    longest = max(len(rig) for rig in rigs)
    reference = rigs[0].positions
    positions = reference.new_zeros(len(rigs), longest, 3)
    intensities = reference.new_zeros(len(rigs), longest, 3)
    for b, rig in enumerate(rigs):
        positions[b, : len(rig)] = rig.positions
        intensities[b, : len(rig)] = rig.intensities
    counts = torch.tensor([len(rig) for rig in rigs], dtype=torch.long)
    return positions, intensities, counts


def fibonacci_sphere_directions(count: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(count, 3)`` nearly uniform unit directions (Fibonacci lattice, +y from top to bottom)."""
    if count < 1:
        raise ValueError(f"count must be positive, got {count}")
    k = torch.arange(count, dtype=torch.float64) + 0.5
    y = 1.0 - 2.0 * k / count
    radius = torch.sqrt(torch.clamp(1.0 - y * y, min=0.0))
    azimuth = math.pi * (3.0 - math.sqrt(5.0)) * k
    dirs = torch.stack([radius * torch.sin(azimuth), y, radius * torch.cos(azimuth)], dim=-1)
    return dirs.to(dtype)


def _check_pair(
    first: torch.Tensor, second: torch.Tensor, first_name: str, second_name: str, owner: str
) -> None:
    if not isinstance(first, torch.Tensor) or not isinstance(second, torch.Tensor):
        raise TypeError(f"{owner}: {first_name} and {second_name} must be torch tensors")
    if first.ndim != 2 or first.shape[1] != 3:
        raise ValueError(f"{owner}: {first_name} must be (L, 3), got {tuple(first.shape)}")
    if second.shape != first.shape:
        raise ValueError(
            f"{owner}: {second_name} {tuple(second.shape)} must match {first_name} {tuple(first.shape)}"
        )


def _columns(table: Any) -> Mapping[str, Any]:
    if isinstance(table, Mapping):
        return table
    if hasattr(table, "column_names") and hasattr(table, "column"):
        return {name: table.column(name).to_pylist() for name in table.column_names}
    raise TypeError(f"expected a pyarrow.Table or a mapping of columns, got {type(table).__name__}")


def _vector_column(values: Any, name: str, source: str) -> np.ndarray:
    if hasattr(values, "to_pylist"):
        values = values.to_pylist()
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{source}: column '{name}' must hold 3 numbers per row ({error})") from None
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{source}: column '{name}' must hold 3 numbers per row, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{source}: column '{name}' has non-finite values")
    return array
