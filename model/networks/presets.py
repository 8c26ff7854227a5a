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
class Stage1Preset:
    """Every size and schedule of one stage-1 configuration."""

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

    def replace(self, **changes) -> Stage1Preset:
        """A copy with some fields changed (e.g. ``iterations`` for a short test run)."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> Stage1Preset:
        data = dict(data)
        data["loss"] = LossWeights(**data.get("loss", {}))
        return cls(**data)


PRESETS: dict[str, Stage1Preset] = {
    "tiny": Stage1Preset(
        name="tiny",
        uv_size=64,
        z_id_dim=32,
        z_l_dim=4,
        start_channels=64,
        min_channels=16,
        mesh_hidden=128,
        crop_size=128,
        batch_size=4,
        iterations=600,
        offset_anneal_iterations=200,
        warmup_iterations=200,
        checkpoint_every=100,
        log_every=10,
        image_every=100,
        held_out_cameras=2,
    ),
    "demo": Stage1Preset(
        name="demo",
        uv_size=128,
        z_id_dim=64,
        z_l_dim=4,
        start_channels=128,
        min_channels=16,
        mesh_hidden=256,
        crop_size=128,
        batch_size=4,
        iterations=3000,
        offset_anneal_iterations=1000,
        warmup_iterations=600,
        checkpoint_every=250,
        log_every=20,
        image_every=250,
        held_out_cameras=2,
    ),
    "small": Stage1Preset(
        name="small",
        uv_size=256,
        z_id_dim=128,
        z_l_dim=4,
        start_channels=256,
        min_channels=16,
        mesh_hidden=256,
        crop_size=512,
        batch_size=8,
        iterations=60_000,
        offset_anneal_iterations=20_000,
        warmup_iterations=5_000,
        checkpoint_every=1000,
        log_every=50,
        image_every=1000,
        held_out_cameras=4,
    ),
    "paper": Stage1Preset(
        name="paper",
        uv_size=1024,
        z_id_dim=256,
        z_l_dim=4,
        start_channels=256,
        min_channels=16,
        mesh_hidden=256,
        crop_size=1024,
        batch_size=8,
        iterations=300_000,
        offset_anneal_iterations=100_000,
        warmup_iterations=20_000,
        checkpoint_every=5000,
        log_every=100,
        image_every=5000,
        held_out_cameras=8,
    ),
}


def get_preset(name: str) -> Stage1Preset:
    """The preset called ``name`` (tiny, demo, small, paper)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown stage-1 preset {name!r}; expected one of {', '.join(PRESETS)}") from None


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
class Stage2Preset:
    """Sizes and schedules of the stage-2 relighting network (and of the single-stage baseline).

    The UV size comes from the stage-1 run; the UNet goes down from it to an 8×8 bottleneck.
    """

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

    def replace(self, **changes) -> Stage2Preset:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> Stage2Preset:
        data = dict(data)
        data["loss"] = Stage2LossWeights(**data.get("loss", {}))
        return cls(**data)


STAGE2_PRESETS: dict[str, Stage2Preset] = {
    "tiny": Stage2Preset(
        name="tiny",
        sh_order=3,
        base_channels=16,
        max_channels=64,
        crop_size=128,
        batch_size=4,
        iterations=600,
        normal_anneal_iterations=200,
        albedo_anneal_iterations=200,
    ),
    "demo": Stage2Preset(
        name="demo",
        sh_order=4,
        base_channels=16,
        max_channels=128,
        crop_size=128,
        batch_size=4,
        iterations=3000,
        normal_anneal_iterations=1000,
        albedo_anneal_iterations=1000,
        checkpoint_every=250,
        log_every=20,
    ),
    "small": Stage2Preset(
        name="small",
        sh_order=6,
        base_channels=16,
        max_channels=256,
        crop_size=512,
        batch_size=8,
        iterations=60_000,
        normal_anneal_iterations=10_000,
        albedo_anneal_iterations=20_000,
        checkpoint_every=1000,
        log_every=50,
    ),
    "paper": Stage2Preset(
        name="paper",
        sh_order=8,
        base_channels=16,
        max_channels=256,
        crop_size=1024,
        batch_size=8,
        iterations=300_000,
        normal_anneal_iterations=10_000,
        albedo_anneal_iterations=100_000,
        checkpoint_every=5000,
        log_every=100,
    ),
}


def with_overrides(preset: Stage1Preset | Stage2Preset, **changes) -> Stage1Preset | Stage2Preset:
    """``preset`` with the fields given a value (not None) replaced: a command line's overrides of a preset."""
    given = {name: value for name, value in changes.items() if value is not None}
    return preset.replace(**given) if given else preset


def get_stage2_preset(name: str) -> Stage2Preset:
    """The stage-2 preset called ``name`` (tiny, demo, small, paper)."""
    try:
        return STAGE2_PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown stage-2 preset {name!r}; expected one of {', '.join(STAGE2_PRESETS)}"
        ) from None
