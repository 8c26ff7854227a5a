"""Synthetic subjects: a seed-determined identity on the shared template topology.

A subject changes the template's shape smoothly (head proportions, nose, jaw, chin, ears, cheeks,
brow) by moving every vertex along its direction from the origin, so the surface stays closed and
star-shaped. Its appearance lives in UV textures on the template layout: a linear albedo (skin tone,
blotches, lips, brows, eyes, a darker hair cap) and the two parameters of the specular lobe used by
:mod:`.raytrace` (intensity and roughness).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relightanyone.synth.template import FEATURES, HeadTemplate, feature_weight, template_radius

# Linear RGB skin albedos from very light to very dark; a subject's tone interpolates along this ramp.
SKIN_RAMP = np.array(
    [
        [0.66, 0.45, 0.36],
        [0.52, 0.33, 0.24],
        [0.36, 0.21, 0.14],
        [0.20, 0.11, 0.07],
        [0.10, 0.055, 0.035],
    ]
)
HAIR_PALETTE = np.array(
    [
        [0.015, 0.010, 0.008],  # black
        [0.05, 0.025, 0.012],  # dark brown
        [0.14, 0.07, 0.03],  # brown
        [0.35, 0.24, 0.12],  # blond
        [0.25, 0.06, 0.02],  # red
        [0.30, 0.30, 0.30],  # grey
    ]
)


@dataclass
class SynthSubject:
    """One synthetic identity: its shape on the template topology and its UV textures."""

    name: str
    seed: int
    vertices: np.ndarray  # (V, 3) float64 metres, canonical head space
    albedo: np.ndarray  # (S, S, 3) float32 linear RGB in [0, 1], row 0 at v = 1
    specular_intensity: np.ndarray  # (S, S) float32, scale of the specular lobe
    roughness: np.ndarray  # (S, S) float32 in (0, 1]


def texel_directions(texture_size: int) -> np.ndarray:
    """(S, S, 3) unit direction of each texel centre under the template's equirectangular UV layout."""
    s = texture_size
    u = (np.arange(s) + 0.5) / s
    v = 1.0 - (np.arange(s) + 0.5) / s
    vv, uu = np.meshgrid(v, u, indexing="ij")
    lon = 2 * np.pi * uu - np.pi
    polar = np.pi * (1.0 - vv)
    return np.stack([np.sin(polar) * np.sin(lon), np.cos(polar), np.sin(polar) * np.cos(lon)], axis=-1)


def _random_bumps(directions: np.ndarray, rng: np.random.Generator, count: int, width: float) -> np.ndarray:
    """(N,) smooth random field in about [-1, 1]: a sum of ``count`` Gaussian bumps of random sign."""
    centres = rng.normal(size=(count, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    signs = rng.uniform(-1, 1, size=count)
    dots = directions @ centres.T  # (N, count)
    return (signs * np.exp((dots - 1.0) / width**2)).sum(axis=1)


def _bumps_texture(texture_size: int, rng: np.random.Generator, count: int, width: float) -> np.ndarray:
    """(S*S,) random bump field evaluated on a coarse texel grid and resized (the field is smooth)."""
    coarse = min(texture_size, 64)
    field = _random_bumps(texel_directions(coarse).reshape(-1, 3), rng, count, width).reshape(coarse, coarse)
    if coarse != texture_size:
        field = cv2.resize(field, (texture_size, texture_size), interpolation=cv2.INTER_CUBIC)
    return field.reshape(-1)


def subject_shape(template: HeadTemplate, rng: np.random.Generator) -> np.ndarray:
    """(V, 3) vertices of a random identity: smooth radial changes plus head proportions."""
    d = template.directions
    radius = template_radius(d)
    # Feature amplitudes relative to the template's (nose, chin, ears vary most).
    changes = {
        "nose": rng.normal(0, 0.007),
        "nose_bridge": rng.normal(0, 0.004),
        "chin": rng.normal(0, 0.007),
        "ear_left": rng.normal(0, 0.006),
        "upper_lip": rng.normal(0, 0.002),
        "lower_lip": rng.normal(0, 0.002),
        "brow_left": rng.normal(0, 0.003),
        "cheek_left": rng.normal(0, 0.004),
    }
    for name, delta in changes.items():
        radius = radius + delta * feature_weight(d, *FEATURES[name][:2])
        mirror = name.replace("left", "right")
        if mirror != name:  # faces are near-symmetric: mirror the change with a little asymmetry
            radius = radius + delta * rng.uniform(0.85, 1.15) * feature_weight(d, *FEATURES[mirror][:2])
    jaw_width = rng.normal(0, 0.006)
    for side in (-1.0, 1.0):
        radius = radius + jaw_width * feature_weight(d, (side * 0.8, -0.9, 0.6), (0.3, 0.25))
    radius = radius + 0.003 * _random_bumps(d, rng, 12, 0.5)
    vertices = d * np.maximum(radius, 0.02)[:, None]
    proportions = np.array([rng.normal(1.0, 0.045), rng.normal(1.0, 0.035), rng.normal(1.0, 0.04)])
    return vertices * proportions


def subject_textures(
    texture_size: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Albedo (S,S,3), specular intensity (S,S) and roughness (S,S) float32 maps of a random identity."""
    d = texel_directions(texture_size).reshape(-1, 3)
    tone = rng.uniform(0, len(SKIN_RAMP) - 1)
    low = int(np.floor(tone))
    high = min(low + 1, len(SKIN_RAMP) - 1)
    skin = SKIN_RAMP[low] * (1 - (tone - low)) + SKIN_RAMP[high] * (tone - low)
    skin = skin * rng.uniform(0.92, 1.08, size=3)
    albedo = np.tile(skin, (len(d), 1))
    # Blotches: low-frequency brightness and redness changes.
    albedo *= 1.0 + 0.12 * np.tanh(_bumps_texture(texture_size, rng, 40, 0.25))[:, None]
    redness = np.clip(_bumps_texture(texture_size, rng, 25, 0.18), 0, None)
    albedo *= 1.0 + 0.15 * redness[:, None] * np.array([0.6, -0.4, -0.4])
    # Fine-scale freckle-like detail so textures are not flat.
    fine = cv2.GaussianBlur(
        rng.normal(size=(texture_size, texture_size)), (0, 0), max(texture_size / 200, 0.6)
    )
    albedo *= 1.0 + 0.12 * np.tanh(fine / (fine.std() + 1e-12)).reshape(-1, 1) * 0.5

    lips = np.clip(
        feature_weight(d, *FEATURES["upper_lip"][:2]) + feature_weight(d, *FEATURES["lower_lip"][:2]), 0, 1
    )
    lip_colour = skin * np.array([0.95, 0.55, 0.55]) * rng.uniform(0.7, 1.0)
    albedo = albedo * (1 - lips[:, None]) + lip_colour * lips[:, None]

    hair_colour = HAIR_PALETTE[rng.integers(len(HAIR_PALETTE))] * rng.uniform(0.8, 1.2, size=3)
    brows = np.clip(
        feature_weight(d, *FEATURES["brow_left"][:2]) + feature_weight(d, *FEATURES["brow_right"][:2]), 0, 1
    )
    brows = brows * rng.uniform(0.6, 0.95)
    albedo = albedo * (1 - brows[:, None]) + hair_colour * brows[:, None]

    eyes = np.clip(
        feature_weight(d, *FEATURES["eye_left"][:2]) + feature_weight(d, *FEATURES["eye_right"][:2]), 0, 1
    )
    eye_colour = np.array([0.25, 0.22, 0.2]) * rng.uniform(0.5, 1.0)
    albedo = albedo * (1 - 0.7 * eyes[:, None]) + 0.7 * eye_colour * eyes[:, None]

    # Hair cap: above a wavy hairline on the front, lower on the back of the head.
    hairline = rng.uniform(0.55, 0.75) + 0.05 * _bumps_texture(texture_size, rng, 6, 0.4)
    back = np.clip(-d[:, 2], 0, 1)
    height = d[:, 1] + 0.55 * back  # the cap reaches lower at the back
    ear_gap = feature_weight(d, *FEATURES["ear_left"][:2]) + feature_weight(d, *FEATURES["ear_right"][:2])
    hair = 1.0 / (1.0 + np.exp(-(height - hairline) / 0.03))
    hair = np.clip(hair * (1 - ear_gap), 0, 1)
    albedo = albedo * (1 - hair[:, None]) + hair_colour * hair[:, None]
    albedo = np.clip(albedo, 0.0, 1.0)

    # Specular maps: oilier T-zone, glossy lips, dull rough hair.
    t_zone = np.clip(
        feature_weight(d, (0.0, 0.2, 1.0), (0.12, 0.35)) + feature_weight(d, (0.0, 0.6, 1.0), (0.35, 0.15)),
        0,
        1,
    )
    base_spec = rng.uniform(0.025, 0.06)
    spec = base_spec * (1 + 0.6 * t_zone + 0.5 * lips) * (1 - 0.6 * hair)
    spec *= 1.0 + 0.15 * np.tanh(_bumps_texture(texture_size, rng, 30, 0.2))
    base_rough = rng.uniform(0.35, 0.5)
    rough = base_rough * (1 - 0.3 * t_zone - 0.35 * lips) + 0.3 * hair
    s = texture_size
    return (
        albedo.reshape(s, s, 3).astype(np.float32),
        np.clip(spec, 0.0, 1.0).reshape(s, s).astype(np.float32),
        np.clip(rough, 0.08, 1.0).reshape(s, s).astype(np.float32),
    )


def make_subject(template: HeadTemplate, name: str, seed: int, texture_size: int) -> SynthSubject:
    """The identity ``name`` determined by ``seed``: same seed, same subject (bit for bit)."""
    if texture_size < 8:
        raise ValueError(f"texture_size must be >= 8, got {texture_size}")
    rng = np.random.default_rng(seed)
    vertices = subject_shape(template, rng)
    albedo, specular, roughness = subject_textures(texture_size, rng)
    return SynthSubject(name, int(seed), vertices, albedo, specular, roughness)
