"""Stage-2 training (paper §3.2) and the single-stage baseline (paper §4.3), one trainer.

``train_stage2(Stage2Config)`` trains on the OLAT dataset's full-on (``full``) and OLAT (``olat-KKK``)
training frames; an OLAT frame is lit by its rig light from ``lights.arrow``, a full-on frame by all of
them. Two modes:

* **stage 2** (default): the stage-1 run is loaded and frozen (eval mode, no gradients); every sample's
  Gaussians are decoded with the OLAT dataset's lighting code z_l, and the relighting UNet
  (:class:`relightanyone.model.networks.stage2.Stage2Model`) learns the reflectance from their full-on colours.
* **single stage** (``single_stage=True``): :class:`relightanyone.model.networks.single_stage.SingleStageModel` is
  trained from scratch on the OLAT dataset alone, geometry included (stage 1's geometry terms are added).

Objective per sample: ``10 L1 + 0.2 (1 − SSIM)`` on the masked relit render, plus ``0.01 c−``
(negative diffuse), ``0.01 mono`` (monochrome transfer), ``λ_n ‖δn‖²`` (1 → 0) and, in stage-2 mode,
``λ_ρ ‖ρ − ρ_prior‖²`` (10 → 0.01), with ρ_prior the sample's own full-on texture (stage 2's input colours)
divided by the full-on rig's mean diffuse irradiance factor (so it is in albedo units). A prior shared by
all subjects (their mean texture) lets the network ignore its colour input and predict one albedo for
everyone; the per-subject prior ties ρ to the input from the first iteration. Adam, lr 5e-4.

Data-parallel under ``torchrun`` like stage 1: each process trains on its slice of one global batch, the
gradients are averaged every step and only rank 0 writes the run folder.

Run folder: ``run.json``, ``checkpoint.pt`` (atomic, resumable), ``metrics.json``, ``tensorboard/``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset, load_manifest
from relightanyone.format.schema import LIGHTS_NAME, TEMPLATE_NAME, make_mesh_key
from relightanyone.format.torch_dataset import (
    LEARNED,
    NormalizedTorchDataset,
    image_hwc,
    iteration_loader,
    random_crop,
)
from relightanyone.locking import output_lock
from relightanyone.model.device import loader_workers
from relightanyone.model.networks.gaussians import load_template_binding
from relightanyone.model.networks.precision import check_precision
from relightanyone.model.networks.presets import Stage1Preset, Stage2Preset
from relightanyone.model.networks.reflectance import (
    FULL_ON_PATTERN,
    OLAT_PREFIX,
    albedo_prior_loss,
    annealed_weight,
    batch_lights,
    camera_centres,
    monochrome_transfer_loss,
    negative_diffuse_loss,
    normal_residual_loss,
    pattern_light_indices,
    relight,
)
from relightanyone.model.networks.render import render_gaussians
from relightanyone.model.networks.single_stage import SingleStageModel
from relightanyone.model.networks.stage2 import Stage2Model, head_frame, texel_mesh_normals
from relightanyone.model.train.checkpoint import (
    capture_rng_state,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from relightanyone.model.train.data import view_batch
from relightanyone.model.train.distributed import (
    ProcessGroup,
    average_gradients,
    broadcast_weights,
    setup_process_group,
    sync_report,
)
from relightanyone.model.train.losses import (
    as_floats,
    batch_means,
    composite_over_background,
    geometry_terms,
    geometry_weights,
    masked_l1,
    offset_weight,
    ssim_loss,
    weighted_sum,
)
from relightanyone.model.train.run import load_run
from relightanyone.model.train.run_files import (
    CHECKPOINT_NAME,
    METRICS_NAME,
    RUN_INFO_NAME,
    TRAINED_VIEWS_KEY,
    trained_views,
)
from relightanyone.model.train.sampling import (
    CROP_STREAM,
    background_colours,
    iteration_generator,
)
from relightanyone.progress import progress_bar
from relightanyone.render.lights import full_on_rig_from_table, olat_rig_from_table
from relightanyone.render.sh import lambertian_transfer
from relightanyone.render.shading import point_light_sh

TRAIN_SPLIT = "train"
PATTERN_STREAM = 2  # generator stream of the (full-on or OLAT, row) draws; crops use CROP_STREAM
ARCHITECTURE_FIELDS = ("sh_order", "base_channels", "max_channels")
SINGLE_STAGE_LOSSES = ("background", "masked")


@dataclass
class Stage2Config:
    """One stage-2 (or single-stage) run.

    data: the normalized OLAT dataset folder. stage1_run: the frozen stage-1 run (stage-2 mode only).
    stage1_preset: sizes of the single-stage model (single-stage mode only).
    single_stage_loss: the baseline's image loss, ``"background"`` (render and target composited over a
    random background on the whole crop, as stage 1: coverage counts) or ``"masked"`` (L1 and SSIM inside
    the mask only, as stage 2).
    """

    data: Path
    out: Path
    preset: Stage2Preset
    stage1_run: Path | None = None
    single_stage: bool = False
    stage1_preset: Stage1Preset | None = None
    single_stage_loss: str = "background"
    seed: int = 0
    resume: bool = True
    progress: bool = True
    device: str = "auto"  # a --device value: auto, cpu, cuda, cuda:1, ...
    precision: str = "fp32"  # fp32, or bf16 for the trained conv networks (networks.precision)
    checkpoint_maps: bool = False  # recompute the trained networks' map activations in the backward pass
    loader_workers: int | None = None  # batch loader processes (None: device.loader_workers' default)
    accumulation: int = 1  # micro-batches per step: the batch's gradient, accumulated in parts
    extra_info: dict = field(default_factory=dict)


@dataclass(frozen=True)
class OlatView:
    """One training image row: its item in ``OlatFrames.rows`` and key, identity row, subject name, frame
    and the rig lights that are on."""

    position: int
    key: str
    subject_index: int
    subject: str
    frame: int
    lights: tuple[int, ...]
    full_on: bool = False


class OlatFrames:
    """Full-on and OLAT training rows of one normalized OLAT dataset, with its rig.

    Args:
        dataset_dir: the dataset folder; its rows are read through ``rows``, a
            :class:`~relightanyone.format.torch_dataset.NormalizedTorchDataset` of the training split's
            full-on and OLAT rows with the learned colour matrix applied.
        subject_names: identity rows as ``<dataset>/<subject>``; None makes one per training subject.
    """

    def __init__(self, dataset_dir: Path, subject_names: list[str] | None = None) -> None:

        self.path = Path(dataset_dir)
        self.dataset = NormalizedDataset(self.path)
        self.name = self.dataset.name
        rows = self.dataset.lights()
        if not rows:
            raise InputError(
                f"{self.path}: no lights.arrow; stage 2 needs an OLAT dataset (kind 'olat') with its rig"
            )
        columns = {name: [row[name] for row in rows] for name in rows[0]}
        self.rig = olat_rig_from_table(columns, source=str(self.path / LIGHTS_NAME))
        self.full_on_rig = full_on_rig_from_table(columns, self.rig, source=str(self.path / LIGHTS_NAME))
        index = columns.get("index", list(range(len(rows))))
        light_patterns = {p: int(i) for p, i in zip(columns.get("pattern", []), index, strict=False) if p}
        self.meshes = self.dataset.meshes()
        subjects = sorted(set(NormalizedTorchDataset(self.dataset, splits=TRAIN_SPLIT).column("subject")))
        if subject_names is None:
            subject_names = [f"{self.name}/{s}" for s in subjects]
        missing = [s for s in subjects if f"{self.name}/{s}" not in subject_names]
        if missing:
            raise InputError(
                f"{self.path}: training subjects {missing} have no identity code in the stage-1 run; "
                "train stage 1 with this dataset first"
            )
        self.subjects = list(subject_names)
        patterns = [p for p in self.dataset.patterns if p == FULL_ON_PATTERN or p.startswith(OLAT_PREFIX)]
        self.rows = NormalizedTorchDataset(
            self.dataset, splits=TRAIN_SPLIT, patterns=patterns, colour_matrix=LEARNED
        )
        cols = {n: self.rows.column(n) for n in ("key", "subject", "frame", "pattern")}
        self.full_on: list[OlatView] = []
        self.olat: list[OlatView] = []
        for i, pattern in enumerate(cols["pattern"]):
            lights = pattern_light_indices(pattern, light_patterns, len(self.rig), str(self.path))
            view = OlatView(
                i,
                cols["key"][i],
                self.subjects.index(f"{self.name}/{cols['subject'][i]}"),
                cols["subject"][i],
                int(cols["frame"][i]),
                tuple(lights),
                pattern == FULL_ON_PATTERN,
            )
            (self.full_on if pattern == FULL_ON_PATTERN else self.olat).append(view)
        if not self.full_on and not self.olat:
            raise InputError(f"{self.path}: no 'full' or 'olat-KKK' training rows")

    def trained_views(self) -> dict[str, list[str]]:
        """{``<dataset>/<subject>``: cameras} of every training row (full-on and OLAT)."""
        subjects, cameras = self.rows.column("subject"), self.rows.column("camera")
        return trained_views((f"{self.name}/{s}", c) for s, c in zip(subjects, cameras, strict=True))

    def draw(self, batch_size: int, full_on_fraction: float, seed: int, iteration: int) -> list[OlatView]:
        """The views of one iteration: full-on with probability ``full_on_fraction``, else OLAT (stateless)."""
        rng = iteration_generator(seed, iteration, PATTERN_STREAM)
        views = []
        for _ in range(batch_size):
            wants_full = rng.random() < full_on_fraction
            group = self.full_on if (wants_full and self.full_on) or not self.olat else self.olat
            views.append(group[int(rng.integers(0, len(group)))])
        return views

    def tracked_vertices(self, view: OlatView) -> np.ndarray | None:
        """(V, 3) tracked mesh of the view's frame, else the subject's first frame, else None."""

        exact = self.meshes.get(make_mesh_key(view.subject, view.frame))
        if exact is not None:
            return exact
        keys = sorted(k for k in self.meshes if k.startswith(f"{view.subject}/"))
        return self.meshes[keys[0]] if keys else None

    def load_batch(
        self, views: list[OlatView], crop_size: int, seed: int, iteration: int, first_sample: int = 0
    ) -> dict[str, torch.Tensor]:
        """image (B, 3, c, c), mask and valid (B, 1, c, c), K (B, 3, 3), w2c (B, 4, 4), light_positions and
        light_intensities (B, Lmax, 3), tracked (B, V, 3), has_mesh (B,), subject_index (B,).

        ``views`` are the global batch's samples ``first_sample ..``; each sample's crop is drawn from its
        own generator, so a process's slice is cropped as in a one-process run of the whole batch."""
        items = [
            random_crop(
                self.rows[view.position],
                crop_size,
                iteration_generator(seed, iteration, CROP_STREAM, first_sample + i),
            )
            for i, view in enumerate(views)
        ]
        light_positions, light_intensities = batch_lights(self.rig, [list(v.lights) for v in views])
        for sample, view in enumerate(views):
            if view.full_on:  # the full-on pattern's own intensities (shorter exposures per light)
                light_intensities[sample, : len(view.lights)] = self.full_on_rig.select(
                    list(view.lights)
                ).intensities
        return {
            **view_batch(items, [self.tracked_vertices(v) for v in views], [v.subject_index for v in views]),
            "light_positions": light_positions,
            "light_intensities": light_intensities,
        }


class Stage2Trainer:
    """Builds the model of either mode, draws batches, computes the loss, trains and checkpoints."""

    def __init__(self, config: Stage2Config, group: ProcessGroup | None = None) -> None:
        if config.single_stage_loss not in SINGLE_STAGE_LOSSES:
            raise InputError(
                f"single-stage loss must be one of {', '.join(SINGLE_STAGE_LOSSES)}, got {config.single_stage_loss!r}"
            )
        self.config = config
        self.preset = config.preset
        self.group = group or setup_process_group(config.device)
        self.device = self.group.device
        torch.manual_seed(config.seed)
        if config.single_stage:
            self._build_single_stage()
        else:
            self._build_stage2()
        self.trainable.precision = check_precision(config.precision)
        self.trainable.checkpoint_maps = config.checkpoint_maps
        broadcast_weights(self.trainable, self.group)  # every process starts from rank 0's weights
        self.optimizer = torch.optim.Adam(self.trainable.parameters(), lr=self.preset.learning_rate)
        self.start = 0

    def _build_stage2(self) -> None:

        if self.config.stage1_run is None:
            raise InputError(
                "stage 2 needs the frozen stage-1 run (--stage1 RUN); use --single-stage for the baseline"
            )
        run = load_run(self.config.stage1_run)
        name = load_manifest(self.config.data).info.name
        if name not in run.datasets:
            raise InputError(
                f"{self.config.stage1_run}: stage 1 was not trained on dataset {name!r} "
                f"(it knows {run.datasets}); its lighting code z_l is needed, so train stage 1 with it"
            )
        self.frames = OlatFrames(self.config.data, run.subjects)
        self.stage1 = run.model.to(self.device).eval().requires_grad_(False)
        self.lighting_index = run.datasets.index(self.frames.name)
        self.stage1_preset = run.model.preset
        self.template_path = Path(self.config.stage1_run) / TEMPLATE_NAME
        centre, radius = head_frame(run.model.mesh_decoder.template_vertices)
        self.trainable = Stage2Model(
            run.model.binding,
            centre,
            radius,
            self.preset.sh_order,
            self.preset.base_channels,
            self.preset.max_channels,
        ).to(self.device)
        self.albedo_per_colour, mean_prior = self._albedo_prior()
        self.trainable.albedo_scale.copy_(mean_prior.mean(dim=0).clamp(min=1e-6))
        self.trainable.albedo_per_colour.copy_(self.albedo_per_colour)

    def _build_single_stage(self) -> None:

        if self.config.stage1_preset is None:
            raise ValueError("the single-stage baseline needs a stage-1 preset for its geometry sizes")
        self.stage1_preset = self.config.stage1_preset
        self.frames = OlatFrames(self.config.data)
        self.template_path = Path(self.config.data) / TEMPLATE_NAME
        if not self.template_path.is_file():
            raise FileNotFoundError(
                f"{self.template_path}: template mesh missing; ingest writes it beside manifest.json"
            )
        template_vertices, binding = load_template_binding(self.template_path, self.stage1_preset.uv_size)
        self.trainable = SingleStageModel(
            self.stage1_preset, self.preset.sh_order, template_vertices, binding, len(self.frames.subjects)
        ).to(self.device)
        self.albedo_per_colour = None
        self.trainable.albedo_scale.copy_(self._albedo_scale_from_images())

    def _diffuse_factor(self, vertices: torch.Tensor, binding, rig) -> torch.Tensor:
        """(3,) mean over Gaussians of Σ_l d_lambert · L_l: the ``rig``'s diffuse light on a unit albedo."""

        transfer = lambertian_transfer(texel_mesh_normals(vertices, binding), self.preset.sh_order)
        rig = rig.to(self.device)
        light_sh = point_light_sh(
            rig.positions[None],
            rig.intensities[None],
            self.preset.sh_order,
            self.trainable.head_centre[None],
            self.preset.inverse_square,
        )
        factor = torch.einsum("bnk,ck->bnc", transfer, light_sh[0]).clamp(min=0.0).mean(dim=(0, 1))
        return factor.clamp(min=1e-12)

    @torch.no_grad()
    def _albedo_prior(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(3,) albedo per full-on colour: one over the full-on rig's mean diffuse factor Σ d_lambert L on
        the OLAT subjects; and (N, 3) the subjects' mean texture in albedo units (sets the albedo unit)."""
        subjects = sorted({v.subject_index for v in self.frames.full_on + self.frames.olat})
        index = torch.tensor(subjects, device=self.device)
        vertices, gaussians = self.stage1(index, torch.full_like(index, self.lighting_index))
        per_colour = 1.0 / self._diffuse_factor(vertices, self.stage1.binding, self.frames.full_on_rig)
        return per_colour, gaussians.colours.mean(dim=0) * per_colour

    @torch.no_grad()
    def _albedo_scale_from_images(self, views: int = 16) -> torch.Tensor:
        """(3,) mean masked full-on pixel over the diffuse factor of the template: the single-stage albedo unit."""
        chosen = (self.frames.full_on or self.frames.olat)[:views]
        totals, count = np.zeros(3), 0.0
        for view in chosen:
            item = self.frames.rows[view.position]
            image, mask = image_hwc(item), item["mask"][0].numpy()
            totals += image[mask > 0].sum(axis=0)
            count += float((mask > 0).sum())
        mean_colour = torch.tensor(totals / max(count, 1.0), dtype=torch.float32, device=self.device)
        template = self.trainable.mesh_decoder.template_vertices[None].to(self.device)
        if self.frames.full_on:
            factor = self._diffuse_factor(template, self.trainable.binding, self.frames.full_on_rig)
        else:  # OLAT frames see one light of the rig
            factor = self._diffuse_factor(template, self.trainable.binding, self.frames.rig)
            factor = factor / max(len(self.frames.rig), 1)
        return (mean_colour / factor).clamp(min=1e-6)

    def make_batch(self) -> functools.partial:
        """The host-side batch of an iteration (:func:`olat_batch`) as a picklable function of it."""
        preset = self.preset
        return functools.partial(
            olat_batch,
            self.frames,
            preset.batch_size,
            preset.batch_size * self.group.world_size,
            self.group.rank * preset.batch_size,
            preset.full_on_fraction,
            preset.crop_size,
            self.config.seed,
        )

    def batch(self, iteration: int) -> dict[str, torch.Tensor]:
        return {k: v.to(self.device) for k, v in self.make_batch()(iteration).items()}

    def decode(self, batch: dict[str, torch.Tensor]):
        """(vertices (B, V, 3), Gaussians, RelightParams, camera positions (B, 3)) of a batch."""

        cameras = camera_centres(batch["w2c"])
        if self.config.single_stage:
            vertices, gaussians, params = self.trainable(batch["subject_index"], cameras)
            return vertices, gaussians, params, cameras
        with torch.no_grad():
            subjects = batch["subject_index"]
            vertices, gaussians = self.stage1(subjects, torch.full_like(subjects, self.lighting_index))
            normals = texel_mesh_normals(vertices, self.stage1.binding)
        return (
            vertices,
            gaussians,
            self.trainable(gaussians.colours, gaussians.means, normals, cameras),
            cameras,
        )

    def loss(
        self, batch: dict[str, torch.Tensor], iteration: int, first_sample: int = 0
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor | float], torch.Tensor]:
        """Total loss (mean over samples), its unweighted terms (batch means as detached 0-d tensors, read
        only when logged; plus the weights and ``total``), the render."""

        weights = self.preset.loss
        vertices, gaussians, params, cameras = self.decode(batch)
        relit = relight(
            params,
            gaussians.means,
            cameras,
            batch["light_positions"],
            batch["light_intensities"],
            self.trainable.head_centre,
            self.preset.lobe_normalization,
            self.preset.inverse_square,
        )
        crop = batch["image"].shape[-1]
        render, alpha = render_gaussians(
            dataclasses.replace(gaussians, colours=relit.colour), batch["K"], batch["w2c"], crop, crop
        )
        compared, image, mask = render, batch["image"], batch["mask"]
        if self.config.single_stage and self.config.single_stage_loss == "background":
            # Its geometry trains: coverage counts, as in stage 1.
            background = background_colours(self.config.seed, iteration, first_sample, render.shape[0])
            compared, image = composite_over_background(
                render, alpha, image, mask, torch.from_numpy(background)
            )
            mask = batch["valid"]  # the whole crop but the padding past the source image
        normal_lambda = annealed_weight(
            iteration, weights.normal_start, weights.normal_end, self.preset.normal_anneal_iterations
        )
        terms = {
            "l1": masked_l1(compared, image, mask),
            "ssim": ssim_loss(compared, image, mask),
            "negative_diffuse": negative_diffuse_loss(relit.diffuse),
            "monochrome": monochrome_transfer_loss(params.transfer),
            "normal": normal_residual_loss(params.normal_residual),
        }
        per_sample = weighted_sum(
            terms,
            {
                "l1": weights.l1,
                "ssim": weights.ssim,
                "negative_diffuse": weights.negative_diffuse,
                "monochrome": weights.monochrome,
                "normal": normal_lambda,
            },
        )
        logged = {"normal_lambda": normal_lambda}
        if self.albedo_per_colour is not None:
            albedo_lambda = annealed_weight(
                iteration, weights.albedo_start, weights.albedo_end, self.preset.albedo_anneal_iterations
            )
            prior = (
                gaussians.colours.detach() * self.albedo_per_colour
            )  # (B, N, 3): each sample's own texture
            terms["albedo"] = albedo_prior_loss(params.albedo, prior, self.trainable.albedo_scale)
            per_sample = per_sample + albedo_lambda * terms["albedo"]
            logged["albedo_lambda"] = albedo_lambda
        if self.config.single_stage:
            geometry = self.stage1_preset.loss
            terms.update(geometry_terms(vertices, batch["tracked"], gaussians, batch["has_mesh"]))
            offset_lambda = offset_weight(iteration, geometry, self.stage1_preset.offset_anneal_iterations)
            per_sample = weighted_sum(terms, geometry_weights(geometry, offset_lambda), per_sample)
        total = per_sample.mean()
        logged.update(batch_means(terms))
        logged["total"] = total.detach()
        return total, logged, render

    def accumulate(self, batch: dict[str, torch.Tensor], iteration: int) -> dict[str, torch.Tensor | float]:
        """Back-propagate the batch's loss in ``config.accumulation`` micro-batches (each loss weighted by its
        share of the samples, so the summed gradient is the whole batch's); returns the batch's terms."""
        size = batch["image"].shape[0]
        first_sample = (
            self.group.rank * self.preset.batch_size
        )  # of this process's slice, in the global batch
        parts = max(1, min(self.config.accumulation, size))
        bounds = [round(size * k / parts) for k in range(parts + 1)]
        terms: dict[str, torch.Tensor | float] = {}
        for begin, end in zip(bounds[:-1], bounds[1:], strict=True):
            share = (end - begin) / size
            micro_batch = {k: v[begin:end] for k, v in batch.items()}
            total, part_terms, _ = self.loss(micro_batch, iteration, first_sample + begin)
            (total * share).backward()
            for name, value in part_terms.items():
                terms[name] = value if name.endswith("_lambda") else terms.get(name, 0.0) + value * share
        return terms

    def resume_if_possible(self) -> None:
        path = Path(self.config.out) / CHECKPOINT_NAME
        if not (self.config.resume and path.is_file()):
            return
        checkpoint = load_checkpoint(path)
        saved = checkpoint["preset"]
        differing = [name for name in ARCHITECTURE_FIELDS if saved[name] != getattr(self.preset, name)]
        if (
            differing
            or checkpoint["single_stage"] != self.config.single_stage
            or checkpoint.get("single_stage_loss", "background") != self.config.single_stage_loss
            or checkpoint["subjects"] != self.frames.subjects
        ):
            raise InputError(
                f"{path}: the checkpoint is from another mode, architecture ({', '.join(differing) or 'same'}) "
                "or subject list; use another --out folder or --no-resume"
            )
        self.trainable.load_state_dict(checkpoint["model"])
        self.optimizer.load_state_dict(checkpoint["optimizer"])
        restore_rng_state(checkpoint["rng"])
        self.start = int(checkpoint["iteration"])

    def train(self) -> dict:
        """Train (or resume) to ``preset.iterations``; returns the metrics written to ``metrics.json``."""
        from torch.utils.tensorboard import SummaryWriter

        out = Path(self.config.out)
        main = self.group.is_main
        self.resume_if_possible()
        writer = None
        if main:
            out.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(self.template_path, out / TEMPLATE_NAME)
            _write_json(out / RUN_INFO_NAME, self._run_info())
            writer = SummaryWriter(str(out / "tensorboard"), purge_step=self.start)
        self.trainable.train()
        mode = "single-stage" if self.config.single_stage else "stage2"
        progress = progress_bar(
            total=self.preset.iterations,
            initial=self.start,
            disable=not (self.config.progress and main),
            desc=mode,
            unit="it",
        )
        first = last = None
        steps = 0
        seconds = 0.0
        on_gpu = self.device.type == "cuda"
        workers = loader_workers(self.device, self.config.loader_workers)
        loader = iteration_loader(self.make_batch(), self.start, self.preset.iterations, workers, on_gpu)
        batches = iter(loader)
        for iteration in range(self.start, self.preset.iterations):
            began = time.perf_counter()
            batch = {k: v.to(self.device, non_blocking=on_gpu) for k, v in next(batches).items()}
            self.optimizer.zero_grad(set_to_none=True)
            terms = self.accumulate(batch, iteration)
            if self.group.distributed:
                average_gradients(self.trainable, self.group.world_size)
            self.optimizer.step()
            seconds += time.perf_counter() - began
            first, last, steps = first or terms, terms, steps + 1
            done = iteration + 1
            progress.update(1)
            # Loss values are read back from the device only every log_every steps.
            if done % self.preset.log_every == 0 or done == self.preset.iterations:
                logged = as_floats(terms)
                progress.set_postfix({k: f"{logged[k]:.4g}" for k in ("total", "l1", "ssim")})
                if writer is not None:
                    for name, value in logged.items():
                        writer.add_scalar(f"loss/{name}", value, done)
            if main and (done % self.preset.checkpoint_every == 0 or done == self.preset.iterations):
                save_checkpoint(out / CHECKPOINT_NAME, self._checkpoint(done))
        progress.close()
        del batches, loader  # stops the loader's worker processes
        metrics = {
            "mode": mode,
            "iterations": self.preset.iterations,
            "seconds_per_iteration": seconds / steps if steps else None,
            "first_losses": as_floats(first) if first else None,
            "last_losses": as_floats(last) if last else None,
            **sync_report(self.trainable, self.group),
        }
        if main:
            writer.close()
            _write_json(out / METRICS_NAME, metrics)
        if self.group.distributed:  # the others leave once rank 0 has written the run
            dist.barrier()
        return metrics

    def _checkpoint(self, iteration: int) -> dict:
        return {
            "iteration": iteration,
            "model": self.trainable.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": capture_rng_state(),
            "preset": self.preset.to_json(),
            "stage1_preset": self.stage1_preset.to_json(),
            "single_stage": self.config.single_stage,
            "single_stage_loss": self.config.single_stage_loss,
            "subjects": self.frames.subjects,
            "dataset": self.frames.name,
            "seed": self.config.seed,
        }

    def _run_info(self) -> dict:
        return {
            "stage": "single-stage" if self.config.single_stage else "stage2",
            "single_stage_loss": self.config.single_stage_loss if self.config.single_stage else None,
            "preset": self.preset.to_json(),
            "stage1_preset": self.stage1_preset.to_json(),
            "stage1_run": str(Path(self.config.stage1_run).resolve()) if self.config.stage1_run else None,
            "dataset": {"name": self.frames.name, "path": str(self.frames.path.resolve())},
            "subjects": self.frames.subjects,
            TRAINED_VIEWS_KEY: self.frames.trained_views(),
            "head_centre": self.trainable.head_centre.tolist(),
            "lights": len(self.frames.rig),
            "frames": {"full_on": len(self.frames.full_on), "olat": len(self.frames.olat)},
            "seed": self.config.seed,
            "template": TEMPLATE_NAME,
            **self.config.extra_info,
        }


def olat_batch(
    frames: OlatFrames,
    batch_size: int,
    global_batch: int,
    first_sample: int,
    full_on_fraction: float,
    crop_size: int,
    seed: int,
    iteration: int,
) -> dict[str, torch.Tensor]:
    """This process's slice (``batch_size`` samples from ``first_sample``) of the global batch of
    ``iteration``, on the host: views drawn (:meth:`OlatFrames.draw`) and loaded
    (:meth:`OlatFrames.load_batch`); a function of the iteration alone."""
    views = frames.draw(global_batch, full_on_fraction, seed, iteration)
    slice_views = views[first_sample : first_sample + batch_size]
    return frames.load_batch(slice_views, crop_size, seed, iteration, first_sample)


def train_stage2(config: Stage2Config) -> dict:
    """Train a stage-2 (or, with ``single_stage``, a single-stage baseline) run; returns its metrics.

    Under torchrun every process trains on its slice of the global batch (``preset.batch_size`` per
    process) and gradients are averaged each step (:mod:`relightanyone.model.train.distributed`). The
    process that writes the run folder (rank 0) holds its lock (:mod:`relightanyone.locking`) for the
    whole run."""
    group = setup_process_group(config.device)
    with output_lock(config.out) if group.is_main else contextlib.nullcontext():
        return Stage2Trainer(config, group).train()


def _write_json(path: Path, payload: dict) -> None:
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(payload, indent=2, sort_keys=True) + "\n")
    os.replace(temporary, path)
