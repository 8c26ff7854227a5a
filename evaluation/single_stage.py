"""Fitting the single-stage baseline (paper §4.3) to an unseen subject, the same way as the two-stage model.

The fit is :class:`relightanyone.model.fit.fitter.Fitter` with the baseline's networks: inversion of z_id and one
RGB intensity per rig light, then finetuning of its decoders (D_mesh, D_g and the two reflectance
decoders) with the same losses, locality regulariser and settings. The result relights under point
lights, which is what Table 1 measures.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import LIGHTS_NAME, TEMPLATE_NAME
from relightanyone.model.fit.avatar import check_pinhole_cameras
from relightanyone.model.fit.fitter import FitSettings, Fitter
from relightanyone.model.fit.views import FitViews
from relightanyone.model.networks.gaussians import (
    Gaussians,
    assemble_gaussians,
    gather_texels,
    load_template_binding,
)
from relightanyone.model.networks.presets import Stage1Preset, Stage2Preset
from relightanyone.model.networks.reflectance import (
    RelightParams,
    activate_relight_params,
    camera_centres,
    relight,
)
from relightanyone.model.networks.render import render_views
from relightanyone.model.networks.single_stage import SingleStageModel
from relightanyone.model.networks.stage2 import texel_mesh_normals, view_directions
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.run_files import CHECKPOINT_NAME, read_run_info
from relightanyone.render.lights import PointLights, full_on_rig_from_table, olat_rig_from_table


@dataclass
class SingleStageRun:
    """A trained single-stage baseline with the OLAT rig of its dataset, and that rig as lit in its
    full-on frames (what a full-on input's lighting starts at)."""

    model: SingleStageModel
    preset: Stage2Preset
    rig: PointLights
    dataset: str
    path: Path
    full_on_rig: PointLights | None = None


def load_single_stage_run(run: str | Path, device: torch.device | str = "cpu") -> SingleStageRun:
    """Load a ``relightanyone train stage2 --single-stage`` run folder, its network and rigs on ``device``."""

    run = Path(run)
    checkpoint_path = run / CHECKPOINT_NAME
    if not checkpoint_path.is_file():
        raise FileNotFoundError(f"{checkpoint_path}: not a trained single-stage run (no checkpoint)")
    checkpoint = load_checkpoint(checkpoint_path)
    if not checkpoint.get("single_stage"):
        raise InputError(f"{run}: a stage-2 run, not a single-stage baseline (trained with --single-stage)")
    info = read_run_info(run)
    stage1_preset = Stage1Preset.from_json(checkpoint["stage1_preset"])
    preset = Stage2Preset.from_json(checkpoint["preset"])
    template_vertices, binding = load_template_binding(run / TEMPLATE_NAME, stage1_preset.uv_size)
    model = SingleStageModel(
        stage1_preset, preset.sh_order, template_vertices, binding, len(checkpoint["subjects"])
    )
    model.load_state_dict(checkpoint["model"])
    dataset_path = Path(info["dataset"]["path"])
    rows = NormalizedDataset(dataset_path).lights()
    if not rows:
        raise InputError(f"{dataset_path}: lights.arrow has no rows; the baseline fit needs the OLAT rig")
    columns = {name: [row[name] for row in rows] for name in rows[0]}
    rig = olat_rig_from_table(columns, source=str(dataset_path / LIGHTS_NAME))
    full_on_rig = full_on_rig_from_table(columns, rig, source=str(dataset_path / LIGHTS_NAME))
    model = model.to(device).eval().requires_grad_(False)
    return SingleStageRun(
        model,
        preset,
        rig.to(device),
        checkpoint["dataset"],
        run,
        None if full_on_rig is None else full_on_rig.to(device),
    )


def decode_single_stage(
    model: SingleStageModel, z_id: torch.Tensor
) -> tuple[torch.Tensor, Gaussians, torch.Tensor]:
    """z_id (B, D) -> vertices (B, V, 3), Gaussians (colours = albedo), raw view-independent maps."""
    vertices = model.mesh_decoder(z_id)
    geometry_maps = model.geometry_decoder(z_id)
    reflectance_maps = model.reflectance_decoder(z_id)
    albedo_maps = torch.nn.functional.softplus(reflectance_maps[:, 0:3]) * model.albedo_scale[:, None, None]
    gaussians = assemble_gaussians(geometry_maps, albedo_maps, vertices, model.binding, model.spacing)
    return vertices, gaussians, reflectance_maps


def single_stage_reflectance(
    model: SingleStageModel,
    z_id: torch.Tensor,
    vertices: torch.Tensor,
    reflectance_maps: torch.Tensor,
    camera_positions: torch.Tensor,
) -> RelightParams:
    """Reflectance of one decoded subject (z_id (1, D)) seen from C cameras (C, 3) -> RelightParams (B = C)."""
    views = camera_positions.shape[0]
    view = view_directions(camera_positions, model.head_centre)
    view_maps = model.view_decoder(torch.cat([z_id.expand(views, -1), view], dim=1))
    return activate_relight_params(
        gather_texels(reflectance_maps, model.binding).expand(views, -1, -1),
        gather_texels(view_maps, model.binding),
        texel_mesh_normals(vertices, model.binding).expand(views, -1, -1),
        model.sh_order,
        model.albedo_scale,
    )


@dataclass
class SingleStageAvatar:
    """A fitted baseline subject: the finetuned network and its code; relights under point lights."""

    model: SingleStageModel
    z_id: torch.Tensor
    preset: Stage2Preset
    scene_intensities: torch.Tensor

    def __post_init__(self) -> None:
        with torch.no_grad():
            self._vertices, gaussians, self._maps = decode_single_stage(self.model, self.z_id)
        self.means, self.quats = gaussians.means[0], gaussians.quats[0]
        self.scales, self.opacities = gaussians.scales[0], gaussians.opacities[0]
        self.head_centre = self.model.head_centre
        self.stage2_preset = self.preset

    @torch.no_grad()
    def reflectance(self, camera_positions: torch.Tensor) -> RelightParams:
        """Reflectance seen from C camera centres (C, 3) -> RelightParams with B = C."""
        return single_stage_reflectance(self.model, self.z_id, self._vertices, self._maps, camera_positions)

    @torch.no_grad()
    def relight(self, cameras, lighting: PointLights, background: torch.Tensor | None = None) -> torch.Tensor:
        """Render into cameras (one size, no distortion) under point lights -> (C, 3, H, W) linear RGB."""

        if not isinstance(lighting, PointLights):
            raise TypeError("the single-stage baseline is evaluated under point lights only")
        width, height = check_pinhole_cameras(cameras)
        w2c, K = cameras.w2c.float(), cameras.K.float()
        positions = camera_centres(w2c)
        vertices, gaussians, maps = decode_single_stage(self.model, self.z_id)
        params = single_stage_reflectance(self.model, self.z_id, vertices, maps, positions)
        views = positions.shape[0]
        colours = relight(
            params,
            gaussians.means.expand(views, -1, -1),
            positions,
            lighting.positions.expand(views, -1, -1),
            lighting.intensities.expand(views, -1, -1),
            self.model.head_centre,
            self.preset.lobe_normalization,
            self.preset.inverse_square,
        ).colour
        image, _ = render_views(gaussians, K, w2c, width, height, colours=colours, background=background)
        return image


class SingleStageFitter(Fitter):
    """:class:`Fitter` with the single-stage network in place of stage 1 + stage 2."""

    def __init__(self, run: SingleStageRun, views: FitViews, settings: FitSettings | None = None) -> None:
        self.run = run
        self.views = views
        self.settings = settings or FitSettings()
        self.reference = run.model.eval().requires_grad_(False)
        self.stage1 = copy.deepcopy(self.reference)  # the network being finetuned (named as in Fitter)
        self.weights = self.reference.preset.loss
        self.spacing = self.reference.spacing
        codes = self.reference.identity_codes.detach()
        self.training_codes = codes
        self.z_id = torch.nn.Parameter(codes.mean(dim=0, keepdim=True).clone())
        self.start_lighting((run.full_on_rig or run.rig).intensities)
        self.history = {"inversion": [], "finetune": []}
        self.inversion_steps = 0
        self.finetune_steps = 0
        # Fitter reads the training codes through self.model (locality codes).
        self.model = _CodeSource(codes)

    def decode(self, network: SingleStageModel, codes: torch.Tensor) -> tuple[torch.Tensor, Gaussians]:
        vertices, gaussians, _ = decode_single_stage(network, codes)
        return vertices, gaussians

    def decoder_parameters(self) -> list[torch.nn.Parameter]:
        network = self.stage1
        decoders = (
            network.mesh_decoder,
            network.geometry_decoder,
            network.reflectance_decoder,
            network.view_decoder,
        )
        return [p for decoder in decoders for p in decoder.parameters()]

    def reflectance(self, view_index: list[int]):
        vertices, gaussians, maps = decode_single_stage(self.stage1, self.z_id)
        w2c, K = self.views.w2c[view_index], self.views.K[view_index]
        params = single_stage_reflectance(self.stage1, self.z_id, vertices, maps, camera_centres(w2c))
        return vertices, gaussians, params, w2c, K

    def shading(self):
        return self.run.rig.positions, self.stage1.head_centre, self.run.preset

    @torch.no_grad()
    def avatar(self, metadata: dict | None = None) -> SingleStageAvatar:
        network = copy.deepcopy(self.stage1).eval().requires_grad_(False)
        return SingleStageAvatar(
            network, self.z_id.detach().clone(), self.run.preset, self.light_intensities().detach().clone()
        )


@dataclass
class _CodeSource:
    training_codes: torch.Tensor
