"""Rendering one avatar into one camera under many lightings with few splats.

Alpha compositing is linear in the per-Gaussian features, so the relit colours of P lightings can be
stacked into one ``3 P``-channel feature and splatted together: the same pixels as P separate renders,
one projection and tile sort instead of P. Lightings go in groups of ``lightings_per_pass`` to bound the
memory of the feature image at large sizes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.model.fit.avatar import prefilter_for_shading, relight_views
from relightanyone.render.envmap import PrefilteredEnvmap, load_envmap

ENVMAP_NAME = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass(frozen=True)
class NamedLighting:
    """A pattern name and its lighting: ``PointLights`` or a ``PrefilteredEnvmap``."""

    pattern: str
    lighting: object


def envmap_pattern(path: Path) -> str:
    """``env-<stem>`` with characters outside ``[A-Za-z0-9._-]`` replaced by ``_``."""
    return "env-" + ENVMAP_NAME.sub("_", Path(path).stem)


def expansion_lightings(
    rig, rig_patterns: list[str], envmaps: list[Path], device: str
) -> list[NamedLighting]:
    """Every rig light alone (``rig_patterns[k]``), the whole rig (``full``) and each environment map.

    Args:
        rig: :class:`~relightanyone.render.lights.PointLights` with L lights at calibrated intensities.
        rig_patterns: L pattern names (``olat-KKK`` of the OLAT dataset's ``lights.arrow``).
        envmaps: lat-long HDR files (``.exr`` / ``.hdr``).
    """

    if len(rig_patterns) != len(rig):
        raise ValueError(f"{len(rig_patterns)} light pattern names for a rig of {len(rig)} lights")
    rig = rig.to(device)
    lightings = [NamedLighting(name, rig.olat(k)) for k, name in enumerate(rig_patterns)]
    lightings.append(NamedLighting("full", rig))
    for path in envmaps:
        chain = prefilter_for_shading(load_envmap(path))
        chain = PrefilteredEnvmap(tuple(level.to(device) for level in chain.levels), chain.sigma_step)
        lightings.append(NamedLighting(envmap_pattern(path), chain))
    names = [item.pattern for item in lightings]
    if len(set(names)) != len(names):
        raise InputError(f"pattern names are not unique: {names}; rename the environment map files")
    return lightings


@torch.no_grad()
def render_lightings(
    avatar,
    K: torch.Tensor,
    w2c: torch.Tensor,
    width: int,
    height: int,
    lightings: list[NamedLighting],
    lightings_per_pass: int = 16,
) -> torch.Tensor:
    """Relit images of the avatar in one pinhole camera.

    Args:
        avatar: :class:`~relightanyone.model.fit.avatar.FittedAvatar` on the render device.
        K: (3, 3) intrinsics; w2c: (4, 4) world-to-camera (float32, on the avatar's device).
        lightings: P lightings (see :func:`expansion_lightings`).
    Returns:
        (P, 3, H, W) linear RGB, black background, clamped to >= 0.
    """

    images = relight_views(
        avatar,
        w2c.reshape(1, 4, 4),
        K.reshape(1, 3, 3),
        width,
        height,
        [item.lighting for item in lightings],
        lightings_per_pass,
    )
    return images[:, 0].clamp(min=0.0)
