"""Fitting the two-stage model to an unseen subject (RelightAnyone §3.3).

Input: one or several images of the subject under an unknown lighting, with their cameras and, when
available, the tracked mesh of that frame, all read from a normalized dataset (subject, frame, camera list).

1. **Inversion.** The identity code z_id starts at the mean of the stage-1 training codes. The unknown
   scene lighting is modelled as the stage-2 dataset's OLAT rig with one free RGB intensity per light
   (optimized in log space, starting at the calibrated rig, i.e. the full-on light). Every step decodes the
   subject with stage 1 (the OLAT dataset's lighting code, so the colours are what stage 2 was trained
   on), relights it with the frozen stage 2 under the current intensities, splats it into the input views
   and minimizes ``10 L1 + 0.2 (1 − SSIM) + 0.4 vertex L2 + λ_id ‖z_id‖²``. Only z_id and the intensities
   move.
2. **Finetuning.** z_id and the lighting stay at the inversion result (the pivot). The stage-1 decoders
   (D_mesh, D_g, D_c) are finetuned on the same objective plus stage 1's scale bound and final ‖δt‖² weight,
   and a *locality regulariser* ``λ_lr · ‖G_θ(z_r) − G_θ₀(z_r)‖²``: codes z_r between the fitted code and
   random training codes are decoded by the finetuned and by the frozen original decoders, and every change
   of their Gaussians (positions, scales, rotations, opacities, colours, mesh; lengths in texel spacings)
   is penalized, so the finetuning changes this subject and leaves the rest of the identity space alone.
   Stage 2 stays frozen throughout.

A subject captured in one of stage 1's own flat-lit datasets is fitted by :class:`DatasetLitFitter`
instead: its input views are rendered as stage 1 renders that dataset's training images (decoded with the
dataset's lighting code, in the Gaussians' own colours, no light to estimate), so the subject's level and
colour come from what stage 1 learned of that dataset, the way an OLAT expansion relights a training
subject. The avatar is decoded with the OLAT code and relit through stage 2 as above.

The result is a :class:`relightanyone.model.fit.avatar.FittedAvatar`.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import LIGHTS_NAME
from relightanyone.model.fit.avatar import FittedAvatar, avatar_from_decoded
from relightanyone.model.fit.views import FitViews, load_fit_views
from relightanyone.model.networks.gaussians import Gaussians
from relightanyone.model.networks.presets import Stage2Preset
from relightanyone.model.networks.reflectance import RelightParams, camera_centres, relight
from relightanyone.model.networks.render import render_views
from relightanyone.model.networks.stage1 import Stage1Model
from relightanyone.model.networks.stage2 import Stage2Model, head_frame, texel_mesh_normals
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.losses import (
    composite_over_background,
    masked_l1,
    offset_l2,
    scale_bound_loss,
    ssim_loss,
    vertex_l2,
    weighted_sum,
)
from relightanyone.model.train.run import load_run
from relightanyone.model.train.run_files import CHECKPOINT_NAME, read_run_info
from relightanyone.model.train.sampling import iteration_generator
from relightanyone.progress import progress_bar
from relightanyone.render.lights import PointLights, full_on_rig_from_table, olat_rig_from_table

VIEW_STREAM = 10  # generator streams of the fit (views per step, locality codes, backgrounds)
LOCALITY_STREAM = 11
BACKGROUND_STREAM = 12
MIN_INTENSITY = 1e-8  # log-parameterised intensities start here for rig lights calibrated at zero
INPUT_LIGHTINGS = ("rig", "dataset")  # how fit inputs are lit: see fit_subject


@dataclass(frozen=True)
class FitSettings:
    """Iterations, learning rates and weights of a fit. Image weights come from the stage-1 preset."""

    inversion_iterations: int = 300
    finetune_iterations: int = 300
    inversion_lr: float = 1e-2  # z_id and log light intensities
    finetune_lr: float = 3e-4  # stage-1 decoder weights (small, as pivotal tuning)
    views_per_step: int = 4
    identity_weight: float = 0.01  # λ_id on ‖z_id‖²
    # λ_I on the mean squared log-ratio of the scene intensities to the rig's full-on light: images fix
    # only the product of reflectance and light, and without a prior the split drifts (see docs/model.md)
    lighting_prior_weight: float = 1.0
    locality_weight: float = 1.0  # λ_lr
    locality_codes: int = 2  # codes z_r per finetuning step
    locality_min_fraction: float = 0.5  # z_r = z + t (z_train − z), t ~ U(min_fraction, 1)
    seed: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        if self.inversion_iterations < 0 or self.finetune_iterations < 0:
            raise InputError("fit iterations must be >= 0")
        if self.views_per_step < 1 or self.locality_codes < 1:
            raise InputError("views_per_step and locality_codes must be >= 1")
        if not 0.0 <= self.locality_min_fraction <= 1.0:
            raise InputError(f"locality_min_fraction must be in [0, 1], got {self.locality_min_fraction}")


@dataclass
class RelightableModel:
    """A trained stage-1 model with the stage-2 network trained on top of it.

    lighting_code: (z_l,) the stage-1 code of the OLAT dataset stage 2 was trained with.
    rig: that dataset's OLAT rig. sources: where the parts came from (for the avatar's metadata).
    """

    stage1: Stage1Model
    lighting_code: torch.Tensor
    stage2: Stage2Model
    stage2_preset: Stage2Preset
    rig: PointLights
    olat_dataset: str
    sources: dict = field(default_factory=dict)
    full_on_rig: PointLights | None = None  # the rig as lit in full-on frames (None: as ``rig``)
    stage1_datasets: tuple[str, ...] = ()  # stage 1's datasets, in the order of its lighting codes

    @property
    def training_codes(self) -> torch.Tensor:
        """(S, z_id) identity codes of the stage-1 training subjects."""
        return self.stage1.identity_codes.detach()

    @property
    def device(self) -> torch.device:
        return self.lighting_code.device

    def dataset_lighting_code(self, dataset: str) -> torch.Tensor:
        """(z_l,) stage 1's lighting code of one of its datasets (zeros in a model without codes)."""
        if dataset not in self.stage1_datasets:
            raise InputError(
                f"stage 1 was not trained on dataset {dataset!r} ({list(self.stage1_datasets)}); "
                "only its own datasets have a lighting code"
            )
        return self.stage1.lighting_codes[self.stage1_datasets.index(dataset)].detach()

    def to(self, device: torch.device | str) -> RelightableModel:
        """This model with its networks moved to ``device`` (in place, as ``nn.Module.to``) and its
        tensors and rigs copied there."""
        return dataclasses.replace(
            self,
            stage1=self.stage1.to(device),
            lighting_code=self.lighting_code.to(device),
            stage2=self.stage2.to(device),
            rig=self.rig.to(device),
            full_on_rig=None if self.full_on_rig is None else self.full_on_rig.to(device),
        )


def load_relightable_model(
    stage1_run: Path, stage2_run: Path, device: torch.device | str = "cpu"
) -> RelightableModel:
    """Load a stage-1 run and the stage-2 run trained on it (not a single-stage baseline run), on ``device``."""
    stage2_run = Path(stage2_run)
    info = read_run_info(stage2_run)
    checkpoint = load_checkpoint(stage2_run / CHECKPOINT_NAME)
    if checkpoint.get("single_stage"):
        raise InputError(
            f"{stage2_run}: a single-stage baseline run; fitting needs a stage-2 run on a stage-1 model"
        )
    run = load_run(stage1_run)
    dataset_name = checkpoint["dataset"]
    if dataset_name not in run.datasets:
        raise InputError(
            f"{stage2_run}: stage 2 was trained on {dataset_name!r}, which stage-1 run {stage1_run} "
            f"does not know ({run.datasets}); pass the stage-1 run stage 2 was trained on"
        )
    dataset_path = Path(info["dataset"]["path"])
    if not (dataset_path / LIGHTS_NAME).is_file():
        raise FileNotFoundError(
            f"{dataset_path / 'lights.arrow'}: the OLAT rig of stage-2 run {stage2_run} is missing "
            "(the fit models the unknown lighting with that rig)"
        )
    preset = Stage2Preset.from_json(checkpoint["preset"])
    centre, radius = head_frame(run.model.mesh_decoder.template_vertices)
    stage2 = Stage2Model(
        run.model.binding, centre, radius, preset.sh_order, preset.base_channels, preset.max_channels
    )
    stage2.load_state_dict(checkpoint["model"])
    rows = NormalizedDataset(dataset_path).lights()
    if not rows:
        raise InputError(
            f"{dataset_path}: lights.arrow has no rows; the fit models the unknown lighting with that rig"
        )
    columns = {name: [row[name] for row in rows] for name in rows[0]}
    rig = olat_rig_from_table(columns, source=str(dataset_path / LIGHTS_NAME))
    full_on_rig = full_on_rig_from_table(columns, rig, source=str(dataset_path / LIGHTS_NAME))
    model = RelightableModel(
        stage1=run.model,
        lighting_code=run.model.lighting_codes[run.datasets.index(dataset_name)].detach().clone(),
        stage2=stage2.eval().requires_grad_(False),
        stage2_preset=preset,
        rig=rig,
        olat_dataset=dataset_name,
        full_on_rig=full_on_rig,
        stage1_datasets=tuple(run.datasets),
        sources={
            "stage1_run": str(Path(stage1_run).resolve()),
            "stage2_run": str(stage2_run.resolve()),
            "olat_dataset": str(dataset_path.resolve()),
        },
    )
    return model.to(device)


def locality_loss(
    current: tuple[torch.Tensor, Gaussians], reference: tuple[torch.Tensor, Gaussians], spacing: float
) -> torch.Tensor:
    """Mean squared change of decoded Gaussians and meshes (B samples) -> (B,).

    Positions, scales and mesh vertices are compared in texel spacings, rotations as unit quaternions,
    opacities and linear colours as they are, so every term is dimensionless and of similar size.
    """
    (vertices, gaussians), (ref_vertices, ref_gaussians) = current, reference
    terms = [
        ((gaussians.means - ref_gaussians.means) / spacing).pow(2).sum(-1).mean(-1),
        ((gaussians.scales - ref_gaussians.scales) / spacing).pow(2).sum(-1).mean(-1),
        (gaussians.quats - ref_gaussians.quats).pow(2).sum(-1).mean(-1),
        (gaussians.opacities - ref_gaussians.opacities).pow(2).mean(-1),
        (gaussians.colours - ref_gaussians.colours).pow(2).sum(-1).mean(-1),
        ((vertices - ref_vertices) / spacing).pow(2).sum(-1).mean(-1),
    ]
    return torch.stack(terms).sum(0)


def locality_codes(
    z_id: torch.Tensor,
    training_codes: torch.Tensor,
    count: int,
    min_fraction: float,
    generator: np.random.Generator,
) -> torch.Tensor:
    """``count`` codes between the fitted code (1, D) and random training codes (S, D) -> (count, D).

    ``z_r = z + t (z_k − z)`` with ``t ~ U(min_fraction, 1)``: other identities and the space towards them,
    kept away from the fitted subject itself.
    """
    # Drawn with NumPy for reproducibility, then moved to the codes' device (a fit may run on CUDA).
    chosen = torch.as_tensor(
        generator.integers(0, training_codes.shape[0], size=count), device=training_codes.device
    )
    fraction = torch.as_tensor(
        generator.uniform(min_fraction, 1.0, size=(count, 1)), dtype=z_id.dtype, device=z_id.device
    )
    return z_id + fraction * (training_codes[chosen] - z_id)


class Fitter:
    """Inversion and finetuning of one subject; ``avatar()`` packs the result.

    The given model's weights are never changed: it is frozen (eval mode, no gradients) and kept as the
    locality reference, while the fitter finetunes a copy of its stage-1 model.
    """

    fits_lighting = True  # the inversion estimates the scene's light intensities

    def __init__(self, model: RelightableModel, views: FitViews, settings: FitSettings | None = None) -> None:
        self.model = model
        self.views = views
        self.settings = settings or FitSettings()
        self.reference = model.stage1.eval().requires_grad_(False)
        self.stage1 = copy.deepcopy(self.reference)
        self.stage2 = model.stage2.eval().requires_grad_(False)
        self.weights = self.reference.preset.loss
        self.spacing = self.reference.spacing
        self.z_l = model.lighting_code.detach().reshape(1, -1)
        # Inversion starts at the mean identity; the unknown lighting starts as the calibrated full-on rig.
        self.z_id = torch.nn.Parameter(model.training_codes.mean(dim=0, keepdim=True).clone())
        self.start_lighting((model.full_on_rig or model.rig).intensities)
        self.history: dict[str, list[dict[str, float]]] = {"inversion": [], "finetune": []}
        self.inversion_steps = 0
        self.finetune_steps = 0

    def start_lighting(self, intensities: torch.Tensor) -> None:
        """Start the scene lighting at ``intensities`` (L, 3), also the centre of its prior."""
        self.log_intensities = torch.nn.Parameter(intensities.clamp(min=MIN_INTENSITY).log().clone())
        self.log_intensities_start = self.log_intensities.detach().clone()

    def light_intensities(self) -> torch.Tensor:
        """(L, 3) current RGB intensity of every rig light."""
        return self.log_intensities.exp()

    def decode(self, network: Stage1Model, codes: torch.Tensor) -> tuple[torch.Tensor, Gaussians]:
        """Geometry and full-on Gaussians of identity codes (B, D_id) under the OLAT lighting code.

        The one place a network turns codes into Gaussians, so another model (the single-stage baseline)
        can reuse the whole fit by overriding it together with :meth:`render`.
        """
        return network.decode(codes, self.z_l.expand(codes.shape[0], -1))

    def decoder_parameters(self) -> list[torch.nn.Parameter]:
        """The stage-1 weights finetuning moves: D_mesh, D_g, D_c."""
        decoders = (self.stage1.mesh_decoder, self.stage1.geometry_decoder, self.stage1.colour_decoder)
        return [p for decoder in decoders for p in decoder.parameters()]

    def step_views(self, step: int, stream_offset: int = 0) -> list[int]:
        """Views of one step: all of them, or ``views_per_step`` drawn without replacement (stateless)."""
        count = len(self.views)
        if count <= self.settings.views_per_step:
            return list(range(count))
        rng = iteration_generator(self.settings.seed, step, VIEW_STREAM + stream_offset)
        return sorted(int(i) for i in rng.choice(count, self.settings.views_per_step, replace=False))

    def reflectance(
        self, view_index: list[int]
    ) -> tuple[torch.Tensor, Gaussians, RelightParams, torch.Tensor, torch.Tensor]:
        """(vertices, Gaussians, reflectance per view (v, N, ...), w2c (v, 4, 4), K (v, 3, 3)) of the
        current fit in some input views."""
        vertices, gaussians = self.decode(self.stage1, self.z_id)
        w2c, K = self.views.w2c[view_index], self.views.K[view_index]
        count = len(view_index)
        normals = texel_mesh_normals(vertices, self.stage1.binding).expand(count, -1, -1)
        params = self.stage2(
            gaussians.colours.expand(count, -1, -1),
            gaussians.means.expand(count, -1, -1),
            normals,
            camera_centres(w2c),
        )
        return vertices, gaussians, params, w2c, K

    def shading(self) -> tuple[torch.Tensor, torch.Tensor, Stage2Preset]:
        """(rig light positions (L, 3), head centre (3,), the preset with the shading options)."""
        return self.model.rig.positions, self.stage2.head_centre, self.model.stage2_preset

    def render(self, view_index: list[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, Gaussians]:
        """Relit render of the current fit in some input views: (images (v, 3, H, W), alphas (v, 1, H, W),
        vertices, Gaussians)."""

        vertices, gaussians, params, w2c, K = self.reflectance(view_index)
        positions, head_centre, preset = self.shading()
        count = len(view_index)
        relit = relight(
            params,
            gaussians.means.expand(count, -1, -1),
            camera_centres(w2c),
            positions.expand(count, -1, -1),
            self.light_intensities().expand(count, -1, -1),
            head_centre,
            preset.lobe_normalization,
            preset.inverse_square,
        )
        height, width = self.views.images.shape[-2:]
        # One splat call: the geometry is shared by the views, the relit colours are per camera (v, N, 3).
        image, alpha = render_views(gaussians, K, w2c, width, height, colours=relit.colour)
        return image, alpha, vertices, gaussians

    def step_backgrounds(self, step: int, count: int, stream_offset: int = 0) -> torch.Tensor:
        """(count, 3) random background colours of one step (stateless, as the views)."""
        rng = iteration_generator(self.settings.seed, step, BACKGROUND_STREAM + stream_offset)
        return torch.from_numpy(rng.random((count, 3)).astype(np.float32)).to(self.z_id.device)

    def data_terms(
        self, view_index: list[int], background: torch.Tensor | None = None
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor, Gaussians]:
        """Photometric and geometry terms (scalars) of some views, with the decoded mesh and Gaussians.

        With ``background`` (v, 3), render and target are compared over it on the whole image (as in
        training: the fit must keep the head opaque inside its mask and empty outside); without, inside
        the mask only.
        """
        render, alpha, vertices, gaussians = self.render(view_index)
        target, mask = self.views.images[view_index], self.views.masks[view_index]
        if background is not None:
            render, target = composite_over_background(render, alpha, target, mask, background)
            # The whole image but the padding past the source (on the device of the images).
            mask = self.views.valid[view_index].to(target.device)
        terms = {
            "l1": masked_l1(render, target, mask).mean(),
            "ssim": ssim_loss(render, target, mask).mean(),
        }
        if self.views.tracked_vertices is not None:
            terms["geometry"] = vertex_l2(vertices, self.views.tracked_vertices[None]).mean()
        return terms, vertices, gaussians

    def data_loss(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        weights = {"l1": self.weights.l1, "ssim": self.weights.ssim, "geometry": self.weights.geometry}
        return weighted_sum(terms, {name: weight for name, weight in weights.items() if name in terms})

    def inversion_loss(self, view_index: list[int], step: int = 0) -> tuple[torch.Tensor, dict[str, float]]:
        """``10 L1 + 0.2 (1 − SSIM) + 0.4 vertex L2 + λ_id ‖z_id‖²`` and its logged terms."""
        terms, _, _ = self.data_terms(view_index, self.step_backgrounds(step, len(view_index)))
        terms["identity"] = self.z_id.pow(2).sum()
        priors = {"identity": self.settings.identity_weight}
        if self.fits_lighting:
            terms["lighting_prior"] = (self.log_intensities - self.log_intensities_start).pow(2).mean()
            priors["lighting_prior"] = self.settings.lighting_prior_weight
        total = weighted_sum(terms, priors, self.data_loss(terms))
        return total, _logged(terms, total)

    def finetune_loss(
        self, view_index: list[int], step: int, locality_weight: float
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Data terms + scale bound + final λ_t ‖δt‖² + ``locality_weight`` × locality regulariser."""
        terms, _, gaussians = self.data_terms(view_index, self.step_backgrounds(step, len(view_index), 1))
        terms["scale"] = scale_bound_loss(gaussians.scales_preclip).mean()
        terms["offset"] = offset_l2(gaussians.offsets).mean()
        total = weighted_sum(
            terms, {"scale": self.weights.scale, "offset": self.weights.offset_end}, self.data_loss(terms)
        )
        if locality_weight > 0:
            rng = iteration_generator(self.settings.seed, step, LOCALITY_STREAM)
            codes = locality_codes(
                self.z_id.detach(),
                self.model.training_codes,
                self.settings.locality_codes,
                self.settings.locality_min_fraction,
                rng,
            )
            with torch.no_grad():
                reference = self.decode(self.reference, codes)
            terms["locality"] = locality_loss(self.decode(self.stage1, codes), reference, self.spacing).mean()
            total = total + locality_weight * terms["locality"]
        return total, _logged(terms, total)

    def invert(self, iterations: int | None = None) -> list[dict[str, float]]:
        """Optimize z_id and the per-light intensities; returns the logged terms of every step."""
        iterations = self.settings.inversion_iterations if iterations is None else iterations
        for parameter in self.decoder_parameters():
            parameter.requires_grad_(False)
        self.z_id.requires_grad_(True)
        self.log_intensities.requires_grad_(self.fits_lighting)
        moved = [self.z_id, self.log_intensities] if self.fits_lighting else [self.z_id]
        optimizer = torch.optim.Adam(moved, lr=self.settings.inversion_lr)
        return self._optimize(
            "inversion", optimizer, iterations, lambda step, views: self.inversion_loss(views, step)
        )

    def finetune(
        self, iterations: int | None = None, locality_weight: float | None = None
    ) -> list[dict[str, float]]:
        """Finetune the stage-1 decoders around the inversion result (z_id and lighting fixed)."""
        iterations = self.settings.finetune_iterations if iterations is None else iterations
        weight = self.settings.locality_weight if locality_weight is None else float(locality_weight)
        self.z_id.requires_grad_(False)
        self.log_intensities.requires_grad_(False)
        parameters = self.decoder_parameters()
        for parameter in parameters:
            parameter.requires_grad_(True)
        optimizer = torch.optim.Adam(parameters, lr=self.settings.finetune_lr)
        return self._optimize(
            "finetune", optimizer, iterations, lambda step, views: self.finetune_loss(views, step, weight)
        )

    def _optimize(
        self, phase: str, optimizer: torch.optim.Optimizer, iterations: int, loss_fn
    ) -> list[dict[str, float]]:
        offset = 0 if phase == "inversion" else 1
        start = self.inversion_steps if phase == "inversion" else self.finetune_steps
        logged = []
        for step in progress_bar(
            range(start, start + iterations),
            desc=f"fit {self.views.subject}: {phase}",
            unit="it",
            disable=not self.settings.progress,
        ):
            total, terms = loss_fn(step, self.step_views(step, offset))
            if not math.isfinite(float(total.detach())):
                raise FloatingPointError(
                    f"fit {phase} step {step}: the loss became {float(total)}; lower the learning rate"
                )
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            optimizer.step()
            logged.append(terms)
        if phase == "inversion":
            self.inversion_steps += iterations
        else:
            self.finetune_steps += iterations
        self.history[phase].extend(logged)
        return logged

    @torch.no_grad()
    def evaluate(self) -> dict[str, float]:
        """Data terms over all input views with the current fit (no gradient)."""
        terms, _, _ = self.data_terms(list(range(len(self.views))))
        return _logged(terms, self.data_loss(terms))

    @torch.no_grad()
    def avatar(self, metadata: dict | None = None) -> FittedAvatar:
        """The fitted subject as a :class:`FittedAvatar` (decoded Gaussians, frozen stage 2, rig, lighting)."""
        vertices, gaussians = self.stage1.decode(self.z_id, self.z_l)
        info = {
            "subject": self.views.subject,
            "dataset": self.views.dataset,
            "frame": self.views.frame,
            "pattern": self.views.pattern,
            "cameras": self.views.cameras,
            "keys": self.views.keys,
            "olat_dataset": self.model.olat_dataset,
            "settings": asdict(self.settings),
            "iterations": {"inversion": self.inversion_steps, "finetune": self.finetune_steps},
            "mesh": "tracked" if self.views.tracked_vertices is not None else "decoded",
            "final_losses": self.evaluate(),
            "z_id": self.z_id[0].tolist(),
            **self.model.sources,
        }
        info.update(metadata or {})
        return avatar_from_decoded(
            vertices,
            gaussians,
            self.views.tracked_vertices,
            self.stage1,
            self.stage2,
            self.model,
            self.light_intensities(),
            info,
        )


class DatasetLitFitter(Fitter):
    """Fit of a subject captured in one of stage 1's flat-lit datasets, under that dataset's lighting code.

    Inversion and finetuning render the input views as stage 1 rendered the dataset's training images:
    decoded with ``input_lighting_code`` (the dataset's z_l), splatted in the Gaussians' own colours. Only
    z_id moves in the inversion; the scene lighting is not estimated, because the dataset's code already
    says how that capture is lit and exposed. :meth:`avatar` is the base class's: decoded with the OLAT
    code, relightable through stage 2, with the rig's full-on light.
    """

    fits_lighting = False

    def __init__(
        self,
        model: RelightableModel,
        views: FitViews,
        input_lighting_code: torch.Tensor,
        settings: FitSettings | None = None,
    ) -> None:
        super().__init__(model, views, settings)
        self.z_l_input = input_lighting_code.detach().reshape(1, -1).to(self.z_l.device)

    def render(self, view_index: list[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, Gaussians]:
        """The current fit as the input dataset shows it: (images (v, 3, H, W), alphas (v, 1, H, W),
        vertices, Gaussians)."""
        vertices, gaussians = self.stage1.decode(self.z_id, self.z_l_input)
        height, width = self.views.images.shape[-2:]
        image, alpha = render_views(
            gaussians, self.views.K[view_index], self.views.w2c[view_index], width, height
        )
        return image, alpha, vertices, gaussians


def make_fitter(
    model: RelightableModel,
    views: FitViews,
    settings: FitSettings | None = None,
    input_dataset: str | None = None,
) -> Fitter:
    """A :class:`DatasetLitFitter` under the lighting code of stage-1 dataset ``input_dataset``, or without
    one a :class:`Fitter` that estimates an unknown lighting of the OLAT rig."""
    if input_dataset is None:
        return Fitter(model, views, settings)
    return DatasetLitFitter(model, views, model.dataset_lighting_code(input_dataset), settings)


def _logged(terms: dict[str, torch.Tensor], total: torch.Tensor) -> dict[str, float]:
    logged = {name: float(value.detach()) for name, value in terms.items()}
    logged["total"] = float(total.detach())
    return logged


def fit_subject(
    stage1_run: Path,
    stage2_run: Path,
    data: Path,
    subject: str,
    frame: int | None = None,
    cameras: list[str] | None = None,
    pattern: str = "full",
    settings: FitSettings | None = None,
    image_scale: float = 1.0,
    out: Path | None = None,
    device: torch.device | str = "cpu",
    input_lighting: str = "rig",
) -> FittedAvatar:
    """Fit a subject of a normalized dataset end to end (inversion, then finetuning) on ``device``; save
    to ``out`` if given.

    ``input_lighting``: ``"rig"``, the images are lit by an unknown lighting of the OLAT rig, estimated
    with the fit (:class:`Fitter`); ``"dataset"``, ``data`` is one of stage 1's own datasets and its
    images are rendered under that dataset's lighting code (:class:`DatasetLitFitter`).
    """
    if input_lighting not in INPUT_LIGHTINGS:
        raise InputError(f"input lighting must be one of {INPUT_LIGHTINGS}, got {input_lighting!r}")
    settings = settings or FitSettings()
    torch.manual_seed(settings.seed)
    model = load_relightable_model(stage1_run, stage2_run, device)
    views = load_fit_views(data, subject, frame, cameras, pattern, image_scale).to(device)
    if (
        views.tracked_vertices is not None
        and views.tracked_vertices.shape != model.stage1.mesh_decoder.template_vertices.shape
    ):
        raise InputError(
            f"{data}: tracked mesh of {subject!r} frame {views.frame} has {views.tracked_vertices.shape[0]} "
            f"vertices, the model's template has {model.stage1.mesh_decoder.template_vertices.shape[0]}"
        )
    input_dataset = NormalizedDataset(data).name if input_lighting == "dataset" else None
    fitter = make_fitter(model, views, settings, input_dataset)
    fitter.invert()
    fitter.finetune()
    avatar = fitter.avatar({"data": str(Path(data).resolve()), "input_lighting": input_lighting})
    if out is not None:
        avatar.save(out)
    return avatar
