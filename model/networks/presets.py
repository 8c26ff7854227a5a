"""Sizes and schedules of the stage-1 model (full-on Gaussian head model).

One code path, four sizes. ``tiny`` runs the tests and the quick demo on a CPU in minutes, ``demo`` is
a little bigger and still CPU-sized, ``small`` is meant for one GPU, ``paper`` follows the RelightAnyone
paper (UV 1024² = 1,048,576 Gaussians, z_id ∈ R²⁵⁶, z_l ∈ R⁴, decoders from an 8×8×256 map doubled
per layer, loss weights of the supplement). Iteration counts of schedules (the δt annealing, the
colour warm-up) are part of the preset so that they scale with the run length.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar, Self


class PresetRecord:
    """What both presets share: copies with changes, and the JSON form stored in checkpoints."""

    loss_weights_type: ClassVar[type]  # the dataclass of the nested ``loss`` field

    def replace(self, **changes) -> Self:
        """A copy with some fields changed (e.g. ``iterations`` for a short test run)."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> Self:
        data = dict(data)
        data["loss"] = cls.loss_weights_type(**data.get("loss", {}))
        return cls(**data)


def preset_table(preset_type: type, columns: tuple[str, ...], rows: list[tuple]) -> dict:
    """``{name: preset}`` from a table whose rows hold the ``columns`` fields (the first is the name)."""
    presets = [preset_type(**dict(zip(columns, row, strict=True))) for row in rows]
    return {preset.name: preset for preset in presets}


def find_preset(presets: dict, name: str, stage: str):
    """The preset called ``name``; a clear error naming the ones that exist."""
    try:
        return presets[name]
    except KeyError:
        raise ValueError(f"unknown {stage} preset {name!r}; expected one of {', '.join(presets)}") from None


@dataclass(frozen=True)
class LossWeights:
    """Weights of the stage-1 objective (paper supplement values by default)."""

    l1: float = 10.0
    ssim: float = 0.2
    geometry: float = 0.4
    scale: float = 0.01
    offset_start: float = 1.0  # λ_t at iteration 0
    offset_end: float = 0.001  # λ_t once annealing is over


@dataclass(frozen=True)
class Stage1Preset(PresetRecord):
    """Every size and schedule of one stage-1 configuration."""

    loss_weights_type: ClassVar[type] = LossWeights

    name: str
    uv_size: int  # side of the UV maps; one Gaussian per valid texel
    z_id_dim: int  # identity code per subject
    z_l_dim: int  # lighting code per dataset
    start_channels: int  # channels of the first 8×8 map of the conv decoders
    min_channels: int  # channels never drop below this while the decoders upsample
    mesh_hidden: int  # width of the mesh decoder's hidden layer
    crop_size: int  # square training crops, in stored-image pixels
    batch_size: int  # views per iteration (per process under torchrun)
    iterations: int
    offset_anneal_iterations: int  # λ_t goes from offset_start to offset_end over these iterations
    warmup_iterations: int  # colour-alignment warm-up run (no z_l) for uncalibrated datasets
    learning_rate: float = 1e-3
    checkpoint_every: int = 100
    log_every: int = 10
    image_every: int = 100
    held_out_cameras: int = 2  # cameras per subject never trained on; used for PSNR/SSIM
    loss: LossWeights = field(default_factory=LossWeights)

    def __post_init__(self) -> None:
        if self.uv_size < 8 or self.uv_size & (self.uv_size - 1):
            raise ValueError(f"preset {self.name!r}: uv_size must be a power of two >= 8, got {self.uv_size}")
        if self.crop_size < 8:
            raise ValueError(f"preset {self.name!r}: crop_size must be >= 8, got {self.crop_size}")
        if self.batch_size < 1 or self.iterations < 1:
            raise ValueError(f"preset {self.name!r}: batch_size and iterations must be positive")

    @property
    def gaussians_upper_bound(self) -> int:
        """Number of UV texels, the most Gaussians one subject can have."""
        return self.uv_size * self.uv_size


PRESETS: dict[str, Stage1Preset] = preset_table(
    Stage1Preset,
    (
        "name",
        "uv_size",
        "z_id_dim",
        "z_l_dim",
        "start_channels",
        "min_channels",
        "mesh_hidden",
        "crop_size",
        "batch_size",
        "iterations",
        "offset_anneal_iterations",
        "warmup_iterations",
        "checkpoint_every",
        "log_every",
        "image_every",
        "held_out_cameras",
    ),
    [
        ("tiny", 64, 32, 4, 64, 16, 128, 128, 4, 600, 200, 200, 100, 10, 100, 2),
        ("demo", 128, 64, 4, 128, 16, 256, 128, 4, 3000, 1000, 600, 250, 20, 250, 2),
        ("small", 256, 128, 4, 256, 16, 256, 512, 8, 60_000, 20_000, 5_000, 1000, 50, 1000, 4),
        ("paper", 1024, 256, 4, 256, 16, 256, 1024, 8, 300_000, 100_000, 20_000, 5000, 100, 5000, 8),
    ],
)


def get_preset(name: str) -> Stage1Preset:
    """The preset called ``name`` (tiny, demo, small, paper)."""
    return find_preset(PRESETS, name, "stage-1")


# Stage 2: the relighting UNet on top of a frozen stage-1 model (paper §3.2), and the single-stage
# baseline (paper §4.3), which shares these losses and schedules.


@dataclass(frozen=True)
class Stage2LossWeights:
    """Weights of the stage-2 objective (paper §3.2). λ_n and λ_ρ are annealed over the preset's schedules."""

    l1: float = 10.0
    ssim: float = 0.2
    negative_diffuse: float = 0.01  # λ_c−: mean of min(c_diffuse, 0)²
    monochrome: float = 0.01  # λ_mono: SH transfer channels pulled to their mean
    normal_start: float = 1.0  # λ_n on the normal residual δn, linear 1 → 0
    normal_end: float = 0.0
    albedo_start: float = 10.0  # λ_ρ on albedo − prior (mean full-on texture), log-linear 10 → 0.01
    albedo_end: float = 0.01


@dataclass(frozen=True)
class Stage2Preset(PresetRecord):
    """Sizes and schedules of the stage-2 relighting network (and of the single-stage baseline).

    The UV size comes from the stage-1 run; the UNet goes down from it to an 8×8 bottleneck.
    """

    loss_weights_type: ClassVar[type] = Stage2LossWeights

    name: str
    sh_order: int  # order of the diffuse SH transfer d (and of the light SH)
    base_channels: int  # channels of the UNet's full-resolution level
    max_channels: int  # channels double per level down to the bottleneck, never above this
    crop_size: int
    batch_size: int
    iterations: int
    normal_anneal_iterations: int
    albedo_anneal_iterations: int
    full_on_fraction: float = 0.25  # share of full-on frames in a batch; the rest are OLAT frames
    learning_rate: float = 5e-4
    lobe_normalization: str = "rgca"  # spherical-Gaussian lobe normalisation (render.shading)
    inverse_square: bool = True  # point-light falloff I / r², see render.lights
    checkpoint_every: int = 100
    log_every: int = 10
    loss: Stage2LossWeights = field(default_factory=Stage2LossWeights)

    def __post_init__(self) -> None:
        if self.sh_order < 0:
            raise ValueError(f"stage-2 preset {self.name!r}: sh_order must be >= 0, got {self.sh_order}")
        if self.base_channels < 1 or self.max_channels < self.base_channels:
            raise ValueError(f"stage-2 preset {self.name!r}: need 1 <= base_channels <= max_channels")
        if self.batch_size < 1 or self.iterations < 1 or self.crop_size < 8:
            raise ValueError(
                f"stage-2 preset {self.name!r}: batch_size, iterations must be positive, crop_size >= 8"
            )
        if not 0.0 <= self.full_on_fraction <= 1.0:
            raise ValueError(f"stage-2 preset {self.name!r}: full_on_fraction must be in [0, 1]")


STAGE2_PRESETS: dict[str, Stage2Preset] = preset_table(
    Stage2Preset,
    (
        "name",
        "sh_order",
        "base_channels",
        "max_channels",
        "crop_size",
        "batch_size",
        "iterations",
        "normal_anneal_iterations",
        "albedo_anneal_iterations",
        "checkpoint_every",
        "log_every",
    ),
    [
        ("tiny", 3, 16, 64, 128, 4, 600, 200, 200, 100, 10),
        ("demo", 4, 16, 128, 128, 4, 3000, 1000, 1000, 250, 20),
        ("small", 6, 16, 256, 512, 8, 60_000, 10_000, 20_000, 1000, 50),
        ("paper", 8, 16, 256, 1024, 8, 300_000, 10_000, 100_000, 5000, 100),
    ],
)


def with_overrides(preset: Stage1Preset | Stage2Preset, **changes) -> Stage1Preset | Stage2Preset:
    """``preset`` with the fields given a value (not None) replaced: a command line's overrides of a preset."""
    given = {name: value for name, value in changes.items() if value is not None}
    return preset.replace(**given) if given else preset


def get_stage2_preset(name: str) -> Stage2Preset:
    """The stage-2 preset called ``name`` (tiny, demo, small, paper)."""
    return find_preset(STAGE2_PRESETS, name, "stage-2")
