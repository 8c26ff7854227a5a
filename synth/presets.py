"""Sizes of the synthetic world.

One code path, four sizes: ``tiny`` serves the tests and the smoke-run demo (seconds), ``demo`` is big
enough for a model to learn something on a laptop (minutes), ``reference`` is the ``demo`` world with five
test and two validation subjects per dataset, the world of the reference evaluation (intervals over
subjects need several), ``paper`` mirrors the real datasets' counts and resolutions (not meant for a CPU).
Subjects are split train / validation / test; only training subjects reach training. Image sizes are (width, height) of the native files each dataset writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace


@dataclass(frozen=True)
class DatasetSize:
    """How many subjects, cameras, frames and lights one synthetic dataset has."""

    train_subjects: int
    test_subjects: int  # held out: ground truth for them goes to answers/
    cameras: int
    image_size: tuple[int, int]  # (width, height) of the written native images
    frames: int = 1  # frames per subject (head poses / video frames)
    lights: int = 0  # rig lights (D1: dome size; D2: ring; D3/D4: flashes)
    val_subjects: int = 0  # held out for model selection and tuning; answers/ has their truth too

    @property
    def subjects(self) -> int:
        """Every subject of the dataset: train, then validation, then test."""
        return self.train_subjects + self.val_subjects + self.test_subjects

    @property
    def held_out_subjects(self) -> int:
        """Subjects with answers: validation and test."""
        return self.val_subjects + self.test_subjects


@dataclass(frozen=True)
class Preset:
    name: str
    template_segments: int  # angular resolution of the procedural template (vertices grow ~ quadratically)
    texture_size: int  # albedo / specular texture side in texels
    supersampling: int  # rays per pixel side (1 = one ray through each pixel centre)
    answer_lights: int  # OLAT lights of the D1 rig used for the answers of flat-lit subjects (<= d1.lights)
    envmap_count: int  # 10x20 environment maps for image-based relighting answers
    d1: DatasetSize
    d2: DatasetSize
    d3: DatasetSize
    d4: DatasetSize
    datasets: tuple[str, ...] = field(default=("d1", "d2", "d3", "d4"))

    def size_of(self, dataset: str) -> DatasetSize:
        if dataset not in self.datasets:
            raise ValueError(f"unknown dataset {dataset!r}; expected one of {', '.join(self.datasets)}")
        return getattr(self, dataset)


def with_held_out(preset: Preset, name: str, test_subjects: int, val_subjects: int) -> Preset:
    """``preset`` renamed, with these test and validation subjects in every dataset (training unchanged)."""
    sizes = {
        dataset: replace(preset.size_of(dataset), test_subjects=test_subjects, val_subjects=val_subjects)
        for dataset in preset.datasets
    }
    return replace(preset, name=name, **sizes)


DEMO = Preset(
    name="demo",
    template_segments=72,
    texture_size=256,
    supersampling=1,
    answer_lights=32,
    envmap_count=4,
    d1=DatasetSize(
        train_subjects=12,
        test_subjects=3,
        val_subjects=1,
        cameras=12,
        image_size=(192, 288),
        lights=32,
    ),
    d2=DatasetSize(
        train_subjects=14,
        test_subjects=2,
        val_subjects=1,
        cameras=24,
        image_size=(167, 256),
        frames=2,
        lights=32,
    ),
    d3=DatasetSize(
        train_subjects=8, test_subjects=2, val_subjects=1, cameras=8, image_size=(256, 192), lights=4
    ),
    d4=DatasetSize(
        train_subjects=8,
        test_subjects=2,
        val_subjects=1,
        cameras=16,
        image_size=(176, 256),
        frames=2,
        lights=8,
    ),
)

PRESETS: dict[str, Preset] = {
    preset.name: preset
    for preset in (
        Preset(
            name="tiny",
            template_segments=48,
            texture_size=128,
            supersampling=1,
            answer_lights=16,
            envmap_count=2,
            d1=DatasetSize(
                train_subjects=3, test_subjects=1, val_subjects=1, cameras=8, image_size=(128, 192), lights=16
            ),
            d2=DatasetSize(
                train_subjects=3, test_subjects=1, cameras=12, image_size=(104, 160), frames=2, lights=24
            ),
            d3=DatasetSize(train_subjects=2, test_subjects=1, cameras=8, image_size=(160, 120), lights=4),
            d4=DatasetSize(
                train_subjects=2, test_subjects=1, cameras=16, image_size=(110, 160), frames=2, lights=8
            ),
        ),
        DEMO,
        with_held_out(DEMO, "reference", test_subjects=5, val_subjects=2),
        Preset(
            name="paper",
            template_segments=160,
            texture_size=1024,
            supersampling=2,
            answer_lights=331,
            envmap_count=10,
            d1=DatasetSize(
                train_subjects=120, test_subjects=19, cameras=40, image_size=(2160, 4096), lights=331
            ),
            d2=DatasetSize(
                train_subjects=236, test_subjects=20, cameras=80, image_size=(667, 1024), frames=4, lights=64
            ),
            d3=DatasetSize(train_subjects=60, test_subjects=6, cameras=8, image_size=(2048, 1536), lights=4),
            d4=DatasetSize(
                train_subjects=200, test_subjects=20, cameras=16, image_size=(2200, 3208), frames=4, lights=8
            ),
        ),
    )
}


def get_preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(PRESETS)}") from None
