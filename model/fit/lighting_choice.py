"""The lighting a fitted avatar is relit or exported under, as chosen on the command line.

Exactly one of:

* an OLAT light K of the avatar's rig, at its calibrated intensity;
* point lights ``x,y,z[,r,g,b]`` in canonical metres with linear RGB radiant intensity (default: the rig's
  mean light);
* an equirectangular environment map (``.exr``/``.hdr``, +y up, centre column in front of the face),
  optionally turned about the vertical axis in N steps (one lighting per step);
* the lighting estimated from the images the avatar was fitted to.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.model.fit.avatar import FittedAvatar, resolve_lighting
from relightanyone.render.envmap import PrefilteredEnvmap, load_envmap, rotate_envmap_yaw
from relightanyone.render.lights import PointLights


@dataclass(frozen=True)
class NamedLighting:
    """A lighting with the label its frames are named by (e.g. ``olat-003``, ``studio-rot005``)."""

    label: str
    lighting: object  # PointLights | DirectionalLights | PrefilteredEnvmap


@dataclass(frozen=True)
class LightingChoice:
    """The lighting options as given: ``olat`` K, ``point_lights`` (``(x, y, z)`` or ``(x, y, z, r, g, b)``
    each, :func:`~relightanyone.model.fit.option_values.parse_point_light`), an ``envmap`` file turned in
    ``rotate`` steps, or ``fitted`` (the fitted input lighting)."""

    olat: int | None = None
    point_lights: tuple[tuple[float, ...], ...] = ()
    envmap: Path | None = None
    fitted: bool = False
    rotate: int = 1

    def check(self) -> None:
        """Raise InputError unless exactly one lighting is given (checked before the avatar is loaded)."""
        given = [
            name
            for name, value in (
                ("--olat", self.olat is not None),
                ("--point-light", bool(self.point_lights)),
                ("--envmap", self.envmap is not None),
                ("--fitted-lighting", self.fitted),
            )
            if value
        ]
        if len(given) != 1:
            found = ", ".join(given) if given else "none"
            raise InputError(
                f"give exactly one lighting: --olat, --point-light, --envmap or --fitted-lighting (got {found})"
            )
        if self.rotate < 1:
            raise InputError(f"--rotate must be >= 1, got {self.rotate}")
        if self.rotate != 1 and self.envmap is None:
            raise InputError("--rotate turns an environment map: use it with --envmap")


def point_lights_from_values(
    lights: Sequence[Sequence[float]], default_intensity: torch.Tensor
) -> PointLights:
    """Point lights from ``(x, y, z[, r, g, b])`` (canonical metres, linear RGB radiant intensity).

    A light without ``r, g, b`` gets ``default_intensity`` (3,), the mean light of the avatar's rig.
    """
    if not lights:
        raise InputError("--point-light: give at least one light as x,y,z[,r,g,b]")
    positions = [list(light[:3]) for light in lights]
    intensities = [list(light[3:]) if len(light) == 6 else default_intensity.tolist() for light in lights]
    return PointLights(
        torch.tensor(positions, dtype=torch.float32), torch.tensor(intensities, dtype=torch.float32)
    )


def rig_mean_intensity(rig: PointLights) -> torch.Tensor:
    """(3,) mean RGB intensity of the rig's lights: the default brightness of a new point light."""
    return rig.intensities.float().mean(dim=0)


def rotate_prefiltered(env: PrefilteredEnvmap, angle_rad: float) -> PrefilteredEnvmap:
    """A prefiltered map turned about +y (``rotate_envmap_yaw`` on every level).

    The angular filter commutes with a turn about the vertical axis, so this equals prefiltering the turned
    map (exactly for whole-column shifts at every level) without filtering again.
    """

    levels = tuple(rotate_envmap_yaw(level, angle_rad) for level in env.levels)
    return PrefilteredEnvmap(levels=levels, sigma_step=env.sigma_step)


def safe_name(text: str) -> str:
    """A file-name-safe version of a camera or lighting name."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "unnamed"


def envmap_lightings(path: Path, rotations: int = 1) -> list[NamedLighting]:
    """An environment map, or ``rotations`` copies of it turned by ``360° i / rotations`` about +y."""

    if rotations < 1:
        raise InputError(f"--rotate must be >= 1, got {rotations}")
    if not Path(path).is_file():
        raise InputError(f"{path}: no such environment map file")
    prefiltered = resolve_lighting(load_envmap(path))
    stem = safe_name(Path(path).stem)
    if rotations == 1:
        return [NamedLighting(stem, prefiltered)]
    return [
        NamedLighting(f"{stem}-rot{i:03d}", rotate_prefiltered(prefiltered, 2 * math.pi * i / rotations))
        for i in range(rotations)
    ]


def chosen_lightings(avatar: FittedAvatar, choice: LightingChoice) -> list[NamedLighting]:
    """The lightings ``choice`` asks for: one, or one per rotation step of an environment map."""
    choice.check()
    if choice.olat is not None:
        if not 0 <= choice.olat < len(avatar.rig):
            raise InputError(
                f"--olat {choice.olat}: the avatar's rig has {len(avatar.rig)} lights, so K must be in "
                f"0..{len(avatar.rig) - 1}"
            )
        return [NamedLighting(f"olat-{choice.olat:03d}", avatar.olat(choice.olat))]
    if choice.point_lights:
        lights = point_lights_from_values(choice.point_lights, rig_mean_intensity(avatar.rig))
        return [NamedLighting("point" if len(lights) == 1 else f"points{len(lights)}", lights)]
    if choice.fitted:
        return [NamedLighting("fitted", avatar.scene_lights())]
    return envmap_lightings(choice.envmap, choice.rotate)
