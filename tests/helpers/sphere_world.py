"""A tiny OLAT + flat-lit world of Lambertian spheres with trained stage-1 / stage-2 runs, for model tests.

The OLAT dataset ``olat``: spheres (the stage-1 test template, radius ``RADIUS``) under a four-light rig,
seen by four cameras. Subjects s00 and s01 are training subjects with full-on and OLAT frames; s02 (a larger,
differently coloured sphere, split "test") has only a full-on frame under an unknown lighting: the rig with
other RGB intensities per light (``SCENE_INTENSITIES``).

The flat-lit dataset ``flat``: f00 (train) and f01 (test) lit by the rig at ``FLAT_INTENSITIES`` (one
full-on frame each). Their true OLAT images are :func:`true_olat_image`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from helpers.stage1_world import RADIUS, sphere_dataset, sphere_image_row, sphere_mesh, tiny_stage1_preset
from relightanyone.format.schema import LightRow
from relightanyone.model.networks.presets import get_stage2_preset
from relightanyone.model.train.stage1 import Stage1Config, train_stage1
from relightanyone.model.train.stage2 import Stage2Config, train_stage2
from relightanyone.render.camera import look_at_w2c

SIZE = 24
LIGHTS = np.array([[0.8, 0.4, 0.6], [-0.8, 0.3, 0.6], [0.0, 0.9, 0.5], [0.0, -0.5, 0.9]])
RIG_INTENSITY = 2.5
# The unseen subject's lighting: the rig's lights with other RGB intensities (light 1 nearly off).
SCENE_INTENSITIES = np.array([[4.0, 3.0, 2.0], [0.2, 0.2, 0.3], [2.0, 2.5, 3.0], [1.0, 1.0, 1.0]])
SUBJECTS = {
    "s00": (1.0, (0.7, 0.5, 0.4), "train"),
    "s01": (1.0, (0.4, 0.6, 0.8), "train"),
    "s02": (1.15, (0.8, 0.45, 0.3), "test"),
}


def lambert_sphere(scale, albedo, K, w2c, positions, intensities):
    """Ray-cast the sphere of radius RADIUS·scale at the origin under point lights: (image (H, W, 3), mask)."""
    c2w = np.linalg.inv(w2c)
    y, x = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    rays = np.stack([(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1], np.ones_like(x)], -1) @ c2w[:3, :3].T
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    origin = c2w[:3, 3]
    b = rays @ origin
    disc = b**2 - (origin @ origin - (RADIUS * scale) ** 2)
    mask = disc > 0
    points = origin + (-b - np.sqrt(np.clip(disc, 0, None)))[..., None] * rays
    normals = points / (RADIUS * scale)
    radiance = np.zeros((*mask.shape, 3))
    for position, intensity in zip(positions, intensities, strict=True):
        offset = position - points
        cosine = np.clip((normals * offset).sum(-1), 0, None) / (offset**2).sum(-1) ** 1.5
        radiance += np.asarray(intensity) * cosine[..., None]
    image = np.where(mask[..., None], np.asarray(albedo) / np.pi * radiance, 0.0).astype(np.float32)
    return image, mask


def sphere_row(dataset: str, subject: str, camera: int, pattern: str, split: str, image, mask, pose=None):
    """The normalized image row of one rendered sphere view (frame 0, camera ``cam{camera:02d}``); ``pose``
    (K, w2c) when the view is not :func:`sphere_camera`'s."""
    K, w2c = pose or sphere_camera(camera)
    name = f"cam{camera:02d}"
    return sphere_image_row(
        dataset, subject, name, pattern, split, K, w2c, image, mask, f"{subject}/{pattern}/{name}.exr"
    )


def rig_lights(intensity: float, name: str = "L", patterns: Sequence[str] | None = None) -> list[LightRow]:
    """The four lights of the rig (:data:`LIGHTS`), each of grey ``intensity``: light k is named
    ``{name}{k}`` and lit alone in ``patterns[k]`` (default ``olat-{k:03d}``)."""
    patterns = patterns or [f"olat-{k:03d}" for k in range(len(LIGHTS))]
    return [
        LightRow(
            index=k, name=f"{name}{k}", position_m=tuple(p), intensity_rgb=(intensity,) * 3, pattern=pattern
        )
        for k, (p, pattern) in enumerate(zip(LIGHTS, patterns, strict=True))
    ]


def write_olat_world(root: Path) -> Path:
    """The OLAT dataset ``root/olat``: s00, s01 (train) under the rig and OLAT; s02 (test) under SCENE_INTENSITIES."""
    rig = np.full((4, 3), RIG_INTENSITY)
    with sphere_dataset(
        root, "olat", "olat", "4-light OLAT rig + full-on", "fit test sphere world", {"name": "fit-world"}
    ) as writer:
        writer.write_lights(rig_lights(RIG_INTENSITY))
        for subject, (scale, albedo, split) in SUBJECTS.items():
            with writer.part(subject) as part:
                part.add_mesh(sphere_mesh(subject, scale))
                for c in range(4):
                    K, w2c = sphere_camera(c)
                    if split == "train":
                        patterns = {"full": (LIGHTS, rig)} | {
                            f"olat-{k:03d}": (LIGHTS[k : k + 1], rig[k : k + 1]) for k in range(4)
                        }
                    else:
                        patterns = {"full": (LIGHTS, SCENE_INTENSITIES)}
                    for pattern, (positions, intensities) in patterns.items():
                        image, mask = lambert_sphere(scale, albedo, K, w2c, positions, intensities)
                        part.add(sphere_row("olat", subject, c, pattern, split, image, mask))
    return root / "olat"


FLAT_INTENSITIES = np.full((4, 3), 1.5)
FLAT_SUBJECTS = {
    "f00": (1.05, (0.6, 0.55, 0.5), "train"),
    "f01": (0.95, (0.5, 0.4, 0.35), "test"),
}


def sphere_camera(c: int) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), w2c (4, 4)) of camera ``cam{c:02d}`` of both datasets."""
    K = np.array([[2.2 * SIZE, 0, (SIZE - 1) / 2], [0, 2.2 * SIZE, (SIZE - 1) / 2], [0, 0, 1.0]])
    angle = 0.5 * (c - 1.5)
    return K, look_at_w2c(0.5 * np.array([np.sin(angle), 0.1, np.cos(angle)]), np.zeros(3), [0.0, 1.0, 0.0])


def true_olat_image(subject: str, camera: int, light: int) -> tuple[np.ndarray, np.ndarray]:
    """(image (SIZE, SIZE, 3), mask) of any subject of either dataset under rig light ``light`` alone."""
    scale, albedo, _ = (SUBJECTS | FLAT_SUBJECTS)[subject]
    K, w2c = sphere_camera(camera)
    return lambert_sphere(scale, albedo, K, w2c, LIGHTS[light : light + 1], np.full((1, 3), RIG_INTENSITY))


def write_flat_world(root: Path) -> Path:
    """The flat-lit dataset ``root/flat`` (kind "flat", no lights.arrow)."""
    with sphere_dataset(
        root, "flat", "flat", "uniform full-on", "fit test sphere world (flat)", {"name": "flat-world"}
    ) as writer:
        for subject, (scale, albedo, split) in FLAT_SUBJECTS.items():
            with writer.part(subject) as part:
                part.add_mesh(sphere_mesh(subject, scale))
                for c in range(4):
                    K, w2c = sphere_camera(c)
                    image, mask = lambert_sphere(scale, albedo, K, w2c, LIGHTS, FLAT_INTENSITIES)
                    part.add(sphere_row("flat", subject, c, "full", split, image, mask))
    return root / "flat"


def tiny_stage2_preset(**changes):
    """A stage-2 preset sized for the sphere world (SH order 2, 8-16 channels, a few iterations)."""
    settings = dict(
        sh_order=2,
        base_channels=8,
        max_channels=16,
        crop_size=SIZE,
        batch_size=2,
        iterations=4,
        normal_anneal_iterations=2,
        albedo_anneal_iterations=2,
        checkpoint_every=4,
        log_every=2,
        learning_rate=5e-3,
    )
    settings.update(changes)
    return get_stage2_preset("tiny").replace(**settings)


def train_ablation_arms(paths: dict[str, Path], stage1_iterations: int = 6) -> dict[str, tuple[Path, Path]]:
    """The lighting-code ablation's other arms on a world with ``flat`` (same data and budget as the main
    runs): ``no-zl`` (stage 1 without lighting codes) and ``colour-matrix`` (the flat dataset aligned by a
    learned 3x3 first, then no lighting codes). Returns arm -> (stage 1, stage 2)."""
    from relightanyone.model.train.colour_warmup import align_colours

    root = paths["root"]
    preset = tiny_stage1_preset(iterations=stage1_iterations, crop_size=SIZE, held_out_cameras=0)
    aligned = root / "aligned-3x3"
    align_colours([paths["data"], paths["flat"]], ("flat",), preset.replace(warmup_iterations=3), aligned)
    arms = {}
    for arm, datasets in (
        ("no-zl", [paths["data"], paths["flat"]]),
        ("colour-matrix", [aligned / "olat", aligned / "flat"]),
    ):
        stage1, stage2 = root / f"{arm}-stage1", root / f"{arm}-stage2"
        config = Stage1Config(datasets, stage1, preset, lighting_code=False, progress=False, evaluate=False)
        train_stage1(config)
        train_stage2(
            Stage2Config(datasets[0], stage2, tiny_stage2_preset(), stage1_run=stage1, progress=False)
        )
        arms[arm] = (stage1, stage2)
    return arms


def build_sphere_world(
    root: Path, flat: bool = False, single_stage: bool = False, stage1_iterations: int = 6
) -> dict[str, Path]:
    """Write the datasets and train the runs. Returns paths: data (the OLAT dataset), flat (when asked),
    stage1 (trained on olat, and flat when asked), stage2, single_stage (when asked), root."""
    paths = {"root": root, "data": write_olat_world(root)}
    datasets = [paths["data"]]
    if flat:
        paths["flat"] = write_flat_world(root)
        datasets.append(paths["flat"])
    paths["stage1"] = root / "stage1"
    train_stage1(
        Stage1Config(
            datasets,
            paths["stage1"],
            tiny_stage1_preset(iterations=stage1_iterations, crop_size=SIZE, held_out_cameras=0),
            progress=False,
            evaluate=False,
        )
    )
    paths["stage2"] = root / "stage2"
    train_stage2(
        Stage2Config(
            paths["data"], paths["stage2"], tiny_stage2_preset(), stage1_run=paths["stage1"], progress=False
        )
    )
    if single_stage:
        paths["single_stage"] = root / "single-stage"
        train_stage2(
            Stage2Config(
                paths["data"],
                paths["single_stage"],
                tiny_stage2_preset(),
                single_stage=True,
                stage1_preset=tiny_stage1_preset(iterations=4, crop_size=SIZE, held_out_cameras=0),
                progress=False,
            )
        )
    return paths
