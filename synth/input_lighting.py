"""The lighting of the evaluation inputs: held-out subjects lit unlike any capture the model is told of.

A fit of a held-out subject must not be given the lighting of its input. The world therefore lights each
held-out subject's evaluation input under a lighting drawn for that subject alone (from the world seed,
the dataset and the subject's name), built on the OLAT rig's full-on lighting:

* a global level, log-uniform in [1/√2, √2] (±3 dB of exposure),
* a colour tint: RGB gains ``(1 + t, 1, 1 − t)`` with t uniform in [−0.2, 0.2] (warmer or cooler light),
* an independent log-normal gain per light (σ = 0.5 in natural log: some lights several times brighter
  than others),
* mixed with a procedural environment map of its own (not one of the answers' maps), which takes a
  share uniform in [0.3, 0.7] of the lighting's weight.

Every component is a non-negative weight per answer light and channel, and the renderer is linear in its
lights, so the input image is ``Σ_k w_k · OLAT_k`` of the subject's true OLAT answer images: exactly the
image the ray tracer would make under those lights (with the environment discretized on the rig, as the
relit answers are). The weights multiply answer images rendered at the answer lights' intensities; the
full-on base is ``full_on_scale`` of them (the OLAT dataset's full-on exposure).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from relightanyone.synth.envmap import olat_relight_weights, procedural_envmaps

LEVEL_RANGE = (2**-0.5, 2**0.5)
TINT_RANGE = 0.2
LIGHT_JITTER_SIGMA = 0.5
ENVMAP_SHARE_RANGE = (0.3, 0.7)
_INPUT_LIGHTING = 4  # seed purpose, beside synth.world's native/subjects/tracking/names streams


@dataclass(frozen=True)
class InputLighting:
    """The lighting of one held-out subject's evaluation input.

    weights: (L, 3) multipliers of the subject's OLAT answer images (one per answer light).
    """

    weights: np.ndarray
    level: float
    tint: tuple[float, float, float]
    envmap_share: float

    def describe(self) -> dict:
        """JSON-ready summary (the weights' total relative to the full-on base is ``level``)."""
        return {
            "level": round(self.level, 4),
            "tint_rgb": [round(v, 4) for v in self.tint],
            "envmap_share": round(self.envmap_share, 4),
            "per_light_jitter_sigma": LIGHT_JITTER_SIGMA,
        }


def input_lighting(
    seed: int,
    dataset_index: int,
    subject: str,
    light_positions: np.ndarray,
    light_intensities: np.ndarray,
    full_on_scale: float,
) -> InputLighting:
    """The input lighting of ``subject`` (deterministic in seed, dataset and name).

    light_positions (L, 3) and light_intensities (L, 3): the answer lights (canonical metres, render
    units); full_on_scale: the full-on exposure of one light relative to its OLAT image.
    """
    name_key = zlib.crc32(subject.encode("utf-8"))
    rng = np.random.default_rng([int(seed), int(dataset_index), _INPUT_LIGHTING, name_key])
    count = len(np.asarray(light_positions).reshape(-1, 3))
    level = float(np.exp(rng.uniform(*np.log(LEVEL_RANGE))))
    t = float(rng.uniform(-TINT_RANGE, TINT_RANGE))
    tint = np.array([1 + t, 1.0, 1 - t])
    jitter = np.exp(rng.normal(0.0, LIGHT_JITTER_SIGMA, size=(count, 1)))
    points = full_on_scale * jitter * tint  # (L, 3)
    share = float(rng.uniform(*ENVMAP_SHARE_RANGE))
    (_, envmap), *_ = procedural_envmaps(1, int(rng.integers(0, 2**31 - 1)))
    environment = olat_relight_weights(envmap, light_positions, light_intensities)
    environment = environment * (points.sum() / max(float(environment.sum()), 1e-12))
    weights = (
        level * ((1 - share) * points + share * environment) / (points.sum() / (count * 3 * full_on_scale))
    )
    return InputLighting(weights.astype(np.float64), level, tuple(float(v) for v in tint), share)
