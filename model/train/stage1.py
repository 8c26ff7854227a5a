"""Stage-1 training: the multi-identity full-on Gaussian head model over several datasets.

``train_stage1(Stage1Config)`` trains into a run folder::

    RUN/run.json          what was trained: preset, datasets, subjects, seed, processes
    RUN/template.obj      the template mesh the UV binding was built from (renders need it)
    RUN/checkpoint.pt     model, optimizer, iteration, random states (atomic; resumes bit-exactly)
    RUN/metrics.json      held-out PSNR/SSIM per dataset and seconds per iteration
    RUN/tensorboard/      scalars and ground truth | render | error strips

Data-parallel: under ``torchrun`` (``WORLD_SIZE`` > 1) every process draws the same global batch and
trains on its slice; gradients are averaged with one all-reduce per step (gloo on CPU, NCCL on GPU), so
all processes keep identical weights. Only rank 0 writes files.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed as dist

from relightanyone.align.colour import linear_to_display
from relightanyone.errors import InputError
from relightanyone.format.schema import TEMPLATE_NAME
from relightanyone.format.torch_dataset import iteration_loader
from relightanyone.locking import output_lock
from relightanyone.model.device import loader_workers
from relightanyone.model.networks.gaussians import load_template_binding
from relightanyone.model.networks.precision import check_precision
from relightanyone.model.networks.presets import Stage1Preset
from relightanyone.model.networks.render import comparison_strip, render_gaussians
from relightanyone.model.networks.stage1 import Stage1Model
from relightanyone.model.train.checkpoint import (
    capture_rng_state,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from relightanyone.model.train.data import Stage1Data
from relightanyone.model.train.distributed import (
    ProcessGroup,
    average_gradients,
    broadcast_weights,
    setup_process_group,
    sync_report,
)
from relightanyone.model.train.held_out import evaluate_held_out
from relightanyone.model.train.losses import (
    as_floats,
    composite_over_background,
    offset_weight,
    stage1_loss,
)
from relightanyone.model.train.memory import StepShape, estimate_stage1, format_memory
from relightanyone.model.train.run_files import (
    CHECKPOINT_NAME,
    METRICS_NAME,
    RUN_INFO_NAME,
    TRAINED_VIEWS_KEY,
    trained_views,
)
from relightanyone.model.train.sampling import background_colours, balanced_batch
from relightanyone.progress import progress_bar

# Fields that shape the network: a checkpoint can only resume a run that agrees on all of them.
ARCHITECTURE_FIELDS = ("uv_size", "z_id_dim", "z_l_dim", "start_channels", "min_channels", "mesh_hidden")


@dataclass
class Stage1Config:
    """One stage-1 run.

    warmup: the colour-alignment warm-up (lighting code off, a 3×3 learned for each ``uncalibrated``
    dataset, raw dataset colours); otherwise normal training with z_l and learned matrices applied on load.
    lighting_code: False trains without lighting codes (the ablation of z_l): datasets share one colour
    decoder input, aligned only by the learned matrices their loaders apply.
    """

    data: list[Path]
    out: Path
    preset: Stage1Preset
    seed: int = 0
    uncalibrated: tuple[str, ...] = ()
    warmup: bool = False
    lighting_code: bool = True
    resume: bool = True
    progress: bool = True
    evaluate: bool = True
    eval_views_per_dataset: int | None = None
    device: str = "auto"  # a --device value: auto, cpu, cuda, cuda:1, ...
    precision: str = "fp32"  # fp32, or bf16 for the conv decoders (networks.precision)
    loader_workers: int | None = None  # batch loader processes (None: device.loader_workers' default)
    extra_info: dict = field(default_factory=dict)


def stage1_batch(
    data: Stage1Data,
    batch_size: int,
    global_batch: int,
    first_sample: int,
    crop_size: int,
    seed: int,
    iteration: int,
) -> dict[str, torch.Tensor]:
    """This process's slice (samples ``first_sample`` onwards) of the global batch of ``iteration``:
    balanced over datasets, cropped (:meth:`Stage1Data.load_batch`); a function of the iteration alone."""
    pairs = balanced_batch(data.views_per_dataset, global_batch, seed, iteration)
    views = [data.train_views[d][v] for d, v in pairs[first_sample : first_sample + batch_size]]
    return data.load_batch(views, crop_size, seed, iteration, first_sample)


def build_model(
    preset: Stage1Preset,
    data: Stage1Data,
    uncalibrated: tuple[str, ...],
    template_path: Path,
    lighting_code: bool = True,
) -> Stage1Model:
    """The stage-1 model for ``data``'s subjects and datasets, bound to the template at the preset's UV size
    (``lighting_code`` False: without lighting codes)."""

    unknown = sorted(set(uncalibrated) - set(data.names))
    if unknown:
        raise InputError(f"--uncalibrated names {unknown} are not among the datasets {data.names}")
    template_vertices, binding = load_template_binding(template_path, preset.uv_size)
    flags = torch.tensor([name in uncalibrated for name in data.names])
    return Stage1Model(
        preset, template_vertices, binding, len(data.subjects), len(data.names), flags, lighting_code
    )


def _check_resumable(
    checkpoint: dict, preset: Stage1Preset, data: Stage1Data, config: Stage1Config, path: Path
) -> None:
    saved = checkpoint["preset"]
    differing = [name for name in ARCHITECTURE_FIELDS if saved[name] != getattr(preset, name)]
    if differing or checkpoint["subjects"] != data.subjects or checkpoint["datasets"] != data.names:
        raise InputError(
            f"{path}: the checkpoint was trained with other settings or data "
            f"({'preset fields ' + ', '.join(differing) if differing else 'subjects/datasets differ'}); "
            "use another --out folder or --no-resume"
        )
    if (
        checkpoint["warmup"] != config.warmup
        or checkpoint["seed"] != config.seed
        or checkpoint.get("lighting_code", True) != config.lighting_code
    ):
        raise InputError(
            f"{path}: the checkpoint is from a run with another seed, warm-up or lighting-code setting; "
            "use another --out"
        )


def _write_json(path: Path, payload: dict) -> None:
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(payload, indent=2, sort_keys=True) + "\n")
    os.replace(temporary, path)


def train_stage1(config: Stage1Config) -> dict:
    """Train (or resume) a stage-1 run; returns the metrics written to ``RUN/metrics.json``.

    The process that writes the run folder (rank 0) holds its lock (:mod:`relightanyone.locking`) for the
    whole run, so a second run into the same folder stops at once.
    """
    group = setup_process_group(config.device)
    with output_lock(config.out) if group.is_main else contextlib.nullcontext():
        return _train_stage1(config, group)


def _train_stage1(config: Stage1Config, group: ProcessGroup) -> dict:
    preset = config.preset
    out = Path(config.out)
    data = Stage1Data(config.data, preset.held_out_cameras, apply_learned_colour=not config.warmup)
    torch.manual_seed(config.seed)
    model = build_model(preset, data, config.uncalibrated, data.template_path, config.lighting_code).to(
        group.device
    )
    model.precision = check_precision(config.precision)
    broadcast_weights(model, group)  # every process starts from rank 0's weights
    optimizer = torch.optim.Adam(model.parameters(), lr=preset.learning_rate)
    start = 0
    checkpoint_path = out / CHECKPOINT_NAME
    if config.resume and checkpoint_path.is_file():
        checkpoint = load_checkpoint(checkpoint_path)
        _check_resumable(checkpoint, preset, data, config, checkpoint_path)
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        restore_rng_state(checkpoint["rng"])
        start = int(checkpoint["iteration"])

    if group.is_main:
        out.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(data.template_path, out / TEMPLATE_NAME)
        _write_json(out / RUN_INFO_NAME, _run_info(config, data, group))
        parameter_count = sum(p.numel() for p in model.parameters())
        print(
            f"stage 1{' colour warm-up' if config.warmup else ''}"
            f"{'' if config.lighting_code else ' without lighting codes'}: {len(data.subjects)} subjects in "
            f"{len(data.names)} datasets, {model.gaussian_count} Gaussians per subject, "
            f"{parameter_count / 1e6:.2f} M parameters, {group.world_size} process(es)"
        )
        shape = StepShape(preset.batch_size, preset.crop_size)
        print(format_memory(estimate_stage1(model, shape, config.precision)))
        if start:
            print(f"resuming {checkpoint_path} at iteration {start}")

    writer = None
    if group.is_main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tensorboard"), purge_step=start)
    use_lighting = not config.warmup
    global_batch = preset.batch_size * group.world_size
    first_sample = group.rank * preset.batch_size
    progress = progress_bar(
        total=preset.iterations,
        initial=start,
        disable=not (config.progress and group.is_main),
        desc="stage1 warm-up" if config.warmup else "stage1",
        unit="it",
    )
    step_seconds = 0.0
    steps = 0
    make_batch = functools.partial(
        stage1_batch, data, preset.batch_size, global_batch, first_sample, preset.crop_size, config.seed
    )
    on_gpu = group.device.type == "cuda"
    loader = iteration_loader(
        make_batch, start, preset.iterations, loader_workers(group.device, config.loader_workers), on_gpu
    )
    batches = iter(loader)
    for iteration in range(start, preset.iterations):
        began = time.perf_counter()
        batch = {k: v.to(group.device, non_blocking=on_gpu) for k, v in next(batches).items()}
        vertices, gaussians = model(batch["subject_index"], batch["dataset_index"], use_lighting=use_lighting)
        render, alpha = render_gaussians(
            gaussians, batch["K"], batch["w2c"], preset.crop_size, preset.crop_size
        )
        if config.warmup:
            render = model.dataset_colour(render, batch["dataset_index"])
        background = background_colours(config.seed, iteration, first_sample, preset.batch_size)
        render_bg, target_bg = composite_over_background(
            render, alpha, batch["image"], batch["mask"], torch.from_numpy(background).to(group.device)
        )
        loss, terms = stage1_loss(
            render_bg,
            target_bg,
            batch["valid"],  # the whole crop but the padding past the source image, which shows no head
            vertices,
            batch["tracked"],
            gaussians,
            preset.loss,
            offset_weight(iteration, preset.loss, preset.offset_anneal_iterations),
            batch["has_mesh"],
        )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if group.world_size > 1:
            average_gradients(model, group.world_size)
        optimizer.step()
        step_seconds += time.perf_counter() - began
        steps += 1
        done = iteration + 1
        progress.update(1)
        # Loss values are read back from the device only every log_every steps.
        if done % preset.log_every == 0 or done == preset.iterations:
            logged = as_floats(terms)
            progress.set_postfix({k: f"{logged[k]:.4g}" for k in ("total", "l1", "ssim", "geometry")})
            if writer is not None:
                for name, value in logged.items():
                    writer.add_scalar(f"loss/{name}", value, done)
                writer.add_scalar("time/seconds_per_iteration", step_seconds / steps, done)
        if writer is not None:
            if done % preset.image_every == 0 or done == preset.iterations:
                strip = comparison_strip(batch["image"][0], render[0].detach(), batch["mask"][0])
                writer.add_image(
                    "train/truth|render|error", linear_to_display(strip), done, dataformats="CHW"
                )
        if group.is_main and (done % preset.checkpoint_every == 0 or done == preset.iterations):
            save_checkpoint(
                checkpoint_path, _checkpoint_payload(model, optimizer, done, preset, data, config)
            )
    progress.close()
    del batches, loader  # stops the loader's worker processes

    metrics = {
        "iterations": preset.iterations,
        "seconds_per_iteration": step_seconds / steps if steps else None,
    }
    metrics.update(sync_report(model, group))
    if config.evaluate:  # every process scores its share of the held-out views
        metrics["held_out"] = evaluate_held_out(
            model, data, use_lighting, max_views_per_dataset=config.eval_views_per_dataset, group=group
        )
        if config.warmup and config.uncalibrated:
            metrics["held_out_with_colour_matrix"] = evaluate_held_out(
                model,
                data,
                use_lighting,
                dataset_colour=True,
                max_views_per_dataset=config.eval_views_per_dataset,
                group=group,
            )
    if group.is_main:
        if config.warmup:
            metrics["colour_matrices"] = {
                name: model.colour_matrices[i].detach().cpu().tolist()
                for i, name in enumerate(data.names)
                if name in config.uncalibrated
            }
        _write_json(out / METRICS_NAME, metrics)
        writer.close()
    if group.world_size > 1:
        dist.barrier()
    return metrics


def _checkpoint_payload(
    model, optimizer, iteration: int, preset: Stage1Preset, data: Stage1Data, config: Stage1Config
) -> dict:
    return {
        "iteration": iteration,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "rng": capture_rng_state(),
        "preset": preset.to_json(),
        "subjects": data.subjects,
        "datasets": data.names,
        "uncalibrated": list(config.uncalibrated),
        "warmup": config.warmup,
        "lighting_code": config.lighting_code,
        "seed": config.seed,
    }


def _run_info(config: Stage1Config, data: Stage1Data, group: ProcessGroup) -> dict:
    return {
        "stage": "stage1-warmup" if config.warmup else "stage1",
        "preset": config.preset.to_json(),
        "datasets": [
            {"name": n, "path": str(d.resolve())} for n, d in zip(data.names, data.dirs, strict=True)
        ],
        "subjects": data.subjects,
        TRAINED_VIEWS_KEY: trained_views(
            (f"{data.names[v.dataset_index]}/{v.subject}", v.camera)
            for views in data.train_views
            for v in views
        ),
        "uncalibrated": list(config.uncalibrated),
        "lighting_code": config.lighting_code,
        "seed": config.seed,
        "processes": group.world_size,
        "template": TEMPLATE_NAME,
        **config.extra_info,
    }
