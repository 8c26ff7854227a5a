"""Peak memory of one training or fitting process, estimated before it runs, and plans that fit a GPU.

An estimate has these parts (bytes):

* ``parameters``, ``gradients``, ``optimizer_state`` (Adam: two moments) of the weights that train, and
  ``frozen`` weights (stage 1 under stage 2, the reference copy of a fit);
* ``activations``: every tensor autograd keeps for the backward pass. They are traced, not modelled: the
  step's networks, shading and losses run once on torch's ``meta`` device (shapes only, no memory is
  touched, so the ``paper`` preset traces in seconds on a laptop) and each storage handed to
  ``saved_tensors_hooks`` is counted once. Under ``bf16`` the UV maps (4-D tensors) are made in
  bfloat16 and count half (:mod:`relightanyone.model.networks.precision`); with checkpointing, a
  checkpointed network's activations are dropped and come back, one network at a time, in the backward
  pass (``recompute``);
* ``backward``: gradients in flight while the backward pass runs, twice the largest saved tensor;
* ``rasterizer``: per camera, the projected Gaussians and their gradients, and the image buffers
  (modelled: the rasterizer's kernels cannot run on the meta device).

:func:`measure_peak_bytes` measures a step on the CPU with torch's allocator profiler; the estimate is
checked against it at small sizes (``tests/test_memory_plan.py``, ``bench/memory.py``).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from relightanyone.model.networks.gaussians import TexelBinding
from relightanyone.model.networks.presets import Stage1Preset, Stage2Preset
from relightanyone.model.networks.reflectance import batch_lights, camera_centres, relight
from relightanyone.model.networks.render import render_gaussians
from relightanyone.model.networks.single_stage import SingleStageModel
from relightanyone.model.networks.stage1 import Stage1Model
from relightanyone.model.networks.stage2 import Stage2Model, head_frame, texel_mesh_normals
from relightanyone.model.train.losses import composite_over_background, geometry_terms, masked_l1, ssim_loss
from relightanyone.render.camera import look_at_w2c
from relightanyone.render.lights import PointLights

FLOAT_BYTES = 4
GIB = 2**30
META = torch.device("meta")
# Floats per Gaussian and camera in the rasterizer: projected mean (2), conic (3), depth, radius (2),
# 3D and 2D covariance (9 + 3), the composited features with depth (4), each with its gradient.
RASTER_FLOATS_PER_GAUSSIAN = 2 * (2 + 3 + 1 + 2 + 9 + 3 + 4)
# Floats per pixel and camera: features with depth (4), alpha, final transmittance, last index (2),
# each with its gradient.
RASTER_FLOATS_PER_PIXEL = 2 * (4 + 1 + 1 + 2)
# The GPUs a plan is made for, in GB as sold (10^9 bytes), and the share of one kept for the CUDA context,
# the allocator's fragmentation and cuDNN workspaces.
GPU_SIZES_GB = (24, 48, 80)
GPU_HEADROOM = 0.1
# Vertices of the planning template when no template mesh is given (a FLAME-sized head).
PLANNING_VERTICES = 5023


@dataclass(frozen=True)
class StepShape:
    """What one step processes: ``batch`` samples, square images of ``crop`` pixels, ``lights`` lights per
    sample (stage 2: the rig size, as a full-on frame lights every light), ``views`` cameras per sample."""

    batch: int
    crop: int
    lights: int = 1
    views: int = 1


@dataclass(frozen=True)
class Trace:
    """What a traced step keeps for its backward pass: bytes of all saved storages, of the largest, and of
    the largest checkpointed network's activations (recomputed in the backward pass)."""

    saved: int
    largest: int
    recompute: int = 0


def saved_tensor_bytes(step: Callable[[], object], exclude: set[int], half_maps: bool = False) -> Trace:
    """Run ``step`` and count the storages autograd saves for backward, each once; storages in
    ``exclude`` (parameters, by ``_cdata``) are not counted. ``half_maps``: 4-D float tensors count two
    bytes per element (what bf16 autocast makes of the UV maps)."""
    saved: dict[int, int] = {}

    def pack(tensor: torch.Tensor) -> torch.Tensor:
        storage = tensor.untyped_storage()
        if storage._cdata not in exclude:
            size = storage.nbytes()
            if half_maps and tensor.dim() == 4 and tensor.dtype == torch.float32:
                size //= 2
            saved[storage._cdata] = size
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        step()
    return Trace(sum(saved.values()), max(saved.values(), default=0))


def _storage_ids(*modules: torch.nn.Module) -> set[int]:
    return {t.untyped_storage()._cdata for m in modules for t in (*m.parameters(), *m.buffers())}


def _module_bytes(module: torch.nn.Module, trainable: bool | None = None) -> int:
    return sum(
        p.numel() * p.element_size()
        for p in module.parameters()
        if trainable is None or p.requires_grad == trainable
    )


def _on_meta(module: torch.nn.Module) -> torch.nn.Module:
    """A copy of ``module`` on the meta device (the original keeps its weights and device)."""
    return copy.deepcopy(module).to(META)


IMAGE_TRACE_SIDE = 32


def image_loss_trace(batch: int, crop: int) -> Trace:
    """What the image terms (background composite, L1, SSIM) of a step on a (B, 3, c, c) render save
    for backward. kornia's SSIM cannot run on the meta device, so one small CPU image is traced and
    scaled: every saved tensor of these terms is per pixel. The render is a leaf here (the rasterizer is
    modelled separately)."""
    side = IMAGE_TRACE_SIDE
    render = torch.zeros(1, 3, side, side, requires_grad=True)
    alpha = torch.zeros(1, 1, side, side, requires_grad=True)
    mask = torch.zeros(1, 1, side, side)

    def step() -> None:
        composited, target = composite_over_background(
            render, alpha, render.detach(), mask, torch.zeros(1, 3)
        )
        ones = torch.ones_like(mask)
        masked_l1(composited, target, ones) + ssim_loss(composited, target, ones)

    trace = saved_tensor_bytes(step, set())
    scale = batch * crop**2 / side**2
    return Trace(int(trace.saved * scale), int(trace.largest * scale))


def _with_image_loss(trace: Trace, shape: StepShape, cameras: int | None = None) -> Trace:
    image = image_loss_trace(cameras or shape.batch, shape.crop)
    return Trace(trace.saved + image.saved, max(trace.largest, image.largest), trace.recompute)


def rasterizer_bytes(gaussians: int, shape: StepShape) -> int:
    """Modelled rasterizer memory of one step: per camera, projected Gaussians and image buffers."""
    cameras = shape.batch * shape.views
    per_camera = gaussians * RASTER_FLOATS_PER_GAUSSIAN + shape.crop**2 * RASTER_FLOATS_PER_PIXEL
    return cameras * per_camera * FLOAT_BYTES


def _estimate(
    trainable: int, frozen: int, trace: Trace, raster: int, checkpointed: bool, other: int = 0
) -> dict[str, int]:
    estimate = {
        "parameters": trainable,
        "gradients": trainable,
        "optimizer_state": 2 * trainable,
        "frozen": frozen + other,
        "activations": trace.saved,
        "recompute": trace.recompute if checkpointed else 0,
        "backward": 2 * trace.largest,
        "rasterizer": raster,
    }
    estimate["total"] = sum(estimate.values())
    return estimate


def unet_recompute_bytes(network: Stage2Model, batch: int, half_maps: bool) -> int:
    """The largest activations of the UNet's checkpointed parts (encoder, the two decoders), each traced
    alone: what the backward pass holds again while it recomputes one of them."""
    unet, size = network.unet, network.unet.uv_size
    maps = torch.zeros(batch, 6, size, size, device=META)
    with torch.no_grad():
        features = unet.encoder(maps)
    bottleneck, skips = features[-1], features[:-1]
    view = torch.zeros(batch, 3, *bottleneck.shape[2:], device=META)
    parts = [
        (unet.encoder, (maps,)),
        (unet.view_independent, (bottleneck, *skips)),
        (unet.view_dependent, (torch.cat([bottleneck, view], dim=1), *skips)),
    ]
    return max(
        saved_tensor_bytes(lambda n=part, i=inputs: n(*i), _storage_ids(part), half_maps).saved
        for part, inputs in parts
    )


def estimate_stage1(model: Stage1Model, shape: StepShape, precision: str = "fp32") -> dict[str, int]:
    """Bytes by part (and ``total``) of one stage-1 training step of ``model`` (on any device)."""
    meta = _on_meta(model)
    batch = shape.batch
    vertex_count = meta.mesh_decoder.template_vertices.shape[0]

    def step() -> None:
        index = torch.zeros(batch, dtype=torch.long, device=META)
        vertices, gaussians = meta(index, index)
        tracked = torch.zeros(batch, vertex_count, 3, device=META)
        geometry = geometry_terms(vertices, tracked, gaussians, torch.ones(batch, device=META))
        sum(geometry.values()).mean()

    trace = _with_image_loss(saved_tensor_bytes(step, _storage_ids(meta), precision == "bf16"), shape)
    raster = rasterizer_bytes(model.gaussian_count, shape)
    return _estimate(_module_bytes(model), 0, trace, raster, checkpointed=False)


def estimate_stage2(
    stage1: Stage1Model,
    stage2: Stage2Model,
    shape: StepShape,
    precision: str = "fp32",
    checkpointed: bool = False,
) -> dict[str, int]:
    """Bytes by part of one stage-2 training step: ``stage1`` frozen, ``stage2`` trained, ``shape.lights``
    lights per sample (a full-on frame lights the whole rig)."""
    frozen, trained = _on_meta(stage1), _on_meta(stage2)
    trained.precision, trained.checkpoint_maps = precision, checkpointed
    batch, count = shape.batch, stage1.gaussian_count
    half = precision == "bf16"

    def step() -> None:
        index = torch.zeros(batch, dtype=torch.long, device=META)
        with torch.no_grad():
            vertices, gaussians = frozen(index, index)
            normals = texel_mesh_normals(vertices, frozen.binding)
        cameras = torch.ones(batch, 3, device=META)
        params = trained(gaussians.colours, gaussians.means, normals, cameras)
        positions, intensities = _lights(batch, shape.lights)
        relit = relight(params, gaussians.means, cameras, positions, intensities, trained.head_centre)
        relit.colour.sum()

    trace = _with_image_loss(saved_tensor_bytes(step, _storage_ids(frozen, trained), half), shape)
    trace = dataclasses.replace(trace, recompute=unet_recompute_bytes(trained, batch, half))
    # The frozen stage 1's decoded Gaussians of the batch are alive through the step (no gradients).
    decoded = batch * count * (3 + 4 + 3 + 1 + 3 + 3 + 3) * FLOAT_BYTES
    raster = rasterizer_bytes(count, shape)
    return _estimate(_module_bytes(stage2), _module_bytes(stage1), trace, raster, checkpointed, decoded)


def estimate_single_stage(
    model: SingleStageModel, shape: StepShape, precision: str = "fp32"
) -> dict[str, int]:
    """Bytes by part of one single-stage baseline training step."""
    meta = _on_meta(model)
    batch = shape.batch
    vertex_count = meta.mesh_decoder.template_vertices.shape[0]
    meta.precision = precision

    def step() -> None:
        index = torch.zeros(batch, dtype=torch.long, device=META)
        cameras = torch.ones(batch, 3, device=META)
        vertices, gaussians, params = meta(index, cameras)
        positions, intensities = _lights(batch, shape.lights)
        relit = relight(params, gaussians.means, cameras, positions, intensities, meta.head_centre)
        tracked = torch.zeros(batch, vertex_count, 3, device=META)
        geometry = geometry_terms(vertices, tracked, gaussians)
        relit.colour.sum() + sum(geometry.values()).sum()

    trace = _with_image_loss(saved_tensor_bytes(step, _storage_ids(meta), precision == "bf16"), shape)
    raster = rasterizer_bytes(model.gaussian_count, shape)
    return _estimate(_module_bytes(model), 0, trace, raster, checkpointed=False)


def estimate_fit(
    stage1: Stage1Model, stage2: Stage2Model, shape: StepShape, precision: str = "fp32"
) -> dict[str, int]:
    """Bytes by part of one finetuning step of a fit (the larger phase): one subject decoded with the
    stage-1 decoders training, stage 2 frozen, ``shape.views`` input views, ``shape.lights`` rig lights,
    plus two locality codes decoded by the copy and by the frozen reference."""
    trained, reference, frozen2 = _on_meta(stage1), _on_meta(stage1), _on_meta(stage2)
    trained.precision = frozen2.precision = precision
    views = shape.views

    def step() -> None:
        code = torch.zeros(1, stage1.preset.z_id_dim, device=META)
        z_l = torch.zeros(1, stage1.preset.z_l_dim, device=META)
        vertices, gaussians = trained.decode(code, z_l)
        normals = texel_mesh_normals(vertices, trained.binding).expand(views, -1, -1)
        cameras = torch.ones(views, 3, device=META)
        params = frozen2(
            gaussians.colours.expand(views, -1, -1), gaussians.means.expand(views, -1, -1), normals, cameras
        )
        positions, intensities = _lights(views, shape.lights)
        means = gaussians.means.expand(views, -1, -1)
        relit = relight(params, means, cameras, positions, intensities, frozen2.head_centre)
        codes = torch.zeros(2, stage1.preset.z_id_dim, device=META)
        with torch.no_grad():
            reference.decode(codes, z_l.expand(2, -1))
        _, local = trained.decode(codes, z_l.expand(2, -1))
        relit.colour.sum() + local.means.sum()

    traced = saved_tensor_bytes(step, _storage_ids(trained, reference, frozen2), precision == "bf16")
    trace = _with_image_loss(traced, shape, cameras=views)
    decoders = _module_bytes(stage1) - stage1.identity_codes.numel() * FLOAT_BYTES
    raster = rasterizer_bytes(stage1.gaussian_count, StepShape(1, shape.crop, views=views))
    frozen = _module_bytes(stage1) + _module_bytes(stage2)  # the reference copy and stage 2
    return _estimate(decoders, frozen, trace, raster, checkpointed=False)


def _lights(batch: int, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, L, 3) positions and intensities of ``count`` lights per sample on the meta device."""
    rig = PointLights(torch.ones(count, 3), torch.ones(count, 3))
    positions, intensities = batch_lights(rig, [list(range(count))] * batch)
    return positions.to(META), intensities.to(META)


def measure_peak_bytes(step: Callable[[], object]) -> int:
    """Peak bytes of CPU tensors while ``step`` runs, over what was allocated before it: torch's
    allocator profiler records every allocation and free; their running sum's maximum is the peak."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as profiler:
        step()
    events = sorted(
        (e for e in profiler.events() if e.self_cpu_memory_usage),
        key=lambda e: e.time_range.start,
    )
    current = peak = 0
    for event in events:
        current += event.self_cpu_memory_usage
        peak = max(peak, current)
    return peak


def planning_template(uv_size: int, vertices: int = PLANNING_VERTICES) -> tuple[torch.Tensor, TexelBinding]:
    """A stand-in template for plans made without a dataset: ``vertices`` points and a binding in which
    every texel is valid, the most Gaussians a UV size allows (a real template covers fewer)."""
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(vertices, 3, generator=generator) * 0.1
    faces = torch.randint(0, vertices, (max(vertices * 2, 1), 3), generator=generator)
    face_index = torch.randint(0, faces.shape[0], (uv_size, uv_size), generator=generator)
    barycentrics = torch.full((uv_size, uv_size, 3), 1.0 / 3.0)
    valid = torch.ones(uv_size, uv_size, dtype=torch.bool)
    return points, TexelBinding.from_maps(face_index, barycentrics, valid, faces)


def stage2_network(stage1: Stage1Model, preset: Stage2Preset) -> Stage2Model:
    """The stage-2 network a trainer would build on ``stage1``."""
    centre, radius = head_frame(stage1.mesh_decoder.template_vertices)
    return Stage2Model(
        stage1.binding, centre, radius, preset.sh_order, preset.base_channels, preset.max_channels
    )


def planning_models(
    preset: Stage1Preset,
    stage2_preset: Stage2Preset,
    template: tuple[torch.Tensor, TexelBinding] | None = None,
) -> tuple[Stage1Model, Stage2Model]:
    """Stage 1 (one subject, one dataset) and stage 2 at the presets' sizes, on the planning template."""
    vertices, binding = template or planning_template(preset.uv_size)
    stage1 = Stage1Model(preset, vertices, binding, 1, 1)
    return stage1, stage2_network(stage1, stage2_preset)


def fits(estimate: dict[str, int], gpu_gb: int) -> bool:
    """Whether an estimate fits a GPU of ``gpu_gb`` GB with its headroom."""
    return estimate["total"] <= gpu_gb * 1e9 * (1.0 - GPU_HEADROOM)


def propose(
    estimate_for: Callable[[int, str, bool], dict[str, int]],
    batch: int,
    gpu_gb: int,
    checkpointing: bool = True,
) -> dict | None:
    """Settings that reach a global batch of ``batch`` on a ``gpu_gb`` GB GPU: the largest per-step batch
    (a divisor of ``batch``, with gradient accumulation over ``batch / step batch`` steps) that fits with
    fp32, else bf16, else (with ``checkpointing``) checkpointed maps in fp32, then bf16. None when nothing
    fits at batch 1.

    ``estimate_for(step_batch, precision, checkpointed)`` gives an estimate.
    """
    divisors = [b for b in range(batch, 0, -1) if batch % b == 0]
    options = [("fp32", False), ("bf16", False)]
    if checkpointing:
        options += [("fp32", True), ("bf16", True)]
    for step_batch in divisors:
        for precision, checkpointed in options:
            estimate = estimate_for(step_batch, precision, checkpointed)
            if fits(estimate, gpu_gb):
                return {
                    "gpu_gb": gpu_gb,
                    "batch": step_batch,
                    "accumulation": batch // step_batch,
                    "precision": precision,
                    "checkpointing": checkpointed,
                    "estimated_gib": round(estimate["total"] / GIB, 2),
                }
    return None


def format_memory(estimate: dict[str, int], title: str = "estimated training memory per process") -> str:
    """One line per part, in MiB."""
    lines = [f"  {name:<20} {value / 2**20:10.1f} MiB" for name, value in estimate.items()]
    return f"{title}:\n" + "\n".join(lines)


def ring_cameras(count: int, crop: int, distance: float = 0.6) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` cameras on a circle around the origin looking at it: K (C, 3, 3), w2c (C, 4, 4)."""
    poses = []
    for index in range(count):
        angle = 2 * math.pi * index / max(count, 1)
        eye = np.array([distance * math.sin(angle), 0.05, distance * math.cos(angle)])
        poses.append(look_at_w2c(eye, np.zeros(3), np.array([0.0, 1.0, 0.0])))
    focal = 1.2 * crop
    K = torch.tensor([[focal, 0.0, (crop - 1) / 2], [0.0, focal, (crop - 1) / 2], [0.0, 0.0, 1.0]])
    return K.repeat(count, 1, 1), torch.tensor(np.stack(poses), dtype=torch.float32)


def _resident_bytes(optimizer: torch.optim.Optimizer, *modules: torch.nn.Module) -> int:
    """Bytes of the weights and the optimizer state that exist before a step starts."""
    state = sum(
        value.numel() * value.element_size()
        for entry in optimizer.state.values()
        for value in entry.values()
        if torch.is_tensor(value) and value.dim() > 0
    )
    return sum(_module_bytes(m) for m in modules) + state


def _measured_step(loss_fn: Callable[[], torch.Tensor], trained: torch.nn.Module, *frozen) -> int:
    """Peak bytes of one optimisation step of ``trained`` (Adam), measured after a first step made the
    optimizer state: the resident weights and state plus the measured peak of the step."""
    optimizer = torch.optim.Adam([p for p in trained.parameters() if p.requires_grad], lr=1e-4)

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        loss_fn().backward()
        optimizer.step()

    step()
    optimizer.zero_grad(set_to_none=True)
    return _resident_bytes(optimizer, trained, *frozen) + measure_peak_bytes(step)


def stage1_step_loss(model: Stage1Model, shape: StepShape) -> Callable[[], torch.Tensor]:
    """The loss of a stage-1 training step of ``model`` on synthetic inputs (ring cameras, grey targets)
    on the model's device: what :func:`measured_stage1` measures and ``bench/gpu.py`` times."""
    device = model.identity_codes.device
    K, w2c = (tensor.to(device) for tensor in ring_cameras(shape.batch, shape.crop))
    index = torch.zeros(shape.batch, dtype=torch.long, device=device)
    tracked = model.mesh_decoder.template_vertices.expand(shape.batch, -1, -1)
    background = torch.rand(shape.batch, 3, device=device)

    def loss() -> torch.Tensor:
        vertices, gaussians = model(index, index)
        render, alpha = render_gaussians(gaussians, K, w2c, shape.crop, shape.crop)
        image = torch.full_like(render, 0.5)
        composited, target = composite_over_background(render, alpha, image, alpha.detach(), background)
        ones = torch.ones_like(alpha)
        image_terms = 10 * masked_l1(composited, target, ones) + 0.2 * ssim_loss(composited, target, ones)
        return (image_terms + sum(geometry_terms(vertices, tracked, gaussians).values())).mean()

    return loss


def stage2_step_loss(
    stage1: Stage1Model, stage2: Stage2Model, shape: StepShape
) -> Callable[[], torch.Tensor]:
    """The loss of a stage-2 training step (``stage1`` frozen, ``shape.lights`` lights per sample) on
    synthetic inputs on the networks' device; see :func:`stage1_step_loss`."""
    device = stage2.head_centre.device
    stage1.eval().requires_grad_(False)
    K, w2c = (tensor.to(device) for tensor in ring_cameras(shape.batch, shape.crop))
    index = torch.zeros(shape.batch, dtype=torch.long, device=device)
    cameras = camera_centres(w2c)
    rig = PointLights(torch.randn(shape.lights, 3), torch.rand(shape.lights, 3))
    positions, intensities = (
        t.to(device) for t in batch_lights(rig, [list(range(shape.lights))] * shape.batch)
    )

    def loss() -> torch.Tensor:
        with torch.no_grad():
            vertices, gaussians = stage1(index, index)
            normals = texel_mesh_normals(vertices, stage1.binding)
        params = stage2(gaussians.colours, gaussians.means, normals, cameras)
        relit = relight(params, gaussians.means, cameras, positions, intensities, stage2.head_centre)
        render, alpha = render_gaussians(
            dataclasses.replace(gaussians, colours=relit.colour), K, w2c, shape.crop, shape.crop
        )
        image, mask = torch.full_like(render, 0.5), alpha.detach()
        return (10 * masked_l1(render, image, mask) + 0.2 * ssim_loss(render, image, mask)).mean()

    return loss


def measured_stage1(model: Stage1Model, shape: StepShape) -> int:
    """Measured peak bytes of one stage-1 training step of ``model`` on the CPU (:func:`stage1_step_loss`)."""
    return _measured_step(stage1_step_loss(model, shape), model)


def measured_stage2(stage1: Stage1Model, stage2: Stage2Model, shape: StepShape) -> int:
    """Measured peak bytes of one stage-2 training step on the CPU (:func:`stage2_step_loss`)."""
    return _measured_step(stage2_step_loss(stage1, stage2, shape), stage2, stage1)
