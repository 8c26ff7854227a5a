"""A fitted, relightable avatar: everything needed to relight one subject without the training data.

``FittedAvatar`` holds

* the decoded per-Gaussian full-on parameters of the fitted (finetuned) stage-1 model: means, rotations,
  scales, opacities and the full-on colours under the OLAT dataset's lighting code, which are the stage-2
  network's input;
* the decoded mesh (the source of the smooth normals n̂) and, when the input had one, the tracked mesh;
* the frozen stage-2 network (its view-dependent outputs need the camera, so the weights are kept rather
  than one decoding);
* the OLAT rig of the stage-2 dataset and the RGB intensities per rig light fitted as the input lighting;
* the head centre, the presets and JSON metadata (subject, inputs, runs, final losses).

Relighting evaluates the RGCA shading (:mod:`relightanyone.model.networks.reflectance`, :mod:`relightanyone.render.shading`)
per camera and splats the relit Gaussians with :func:`relightanyone.render.rasterize.rasterize`. Lighting is
any of: :class:`~relightanyone.render.lights.PointLights` (an OLAT light, the rig, any point lights),
:class:`~relightanyone.render.lights.DirectionalLights`, an environment map (``(3, H, W)`` lat-long tensor,
a :class:`~relightanyone.render.envmap.PrefilteredEnvmap`, or an ``.exr`` / ``.hdr`` path).

The file is one ``torch.save`` archive of tensors, plain numbers and a JSON metadata string, written
atomically, and read with ``weights_only=True`` (a file asking for any other Python object is refused).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.model.networks.gaussians import TexelBinding
from relightanyone.model.networks.presets import Stage1Preset, Stage2Preset
from relightanyone.model.networks.reflectance import RelightParams, camera_centres, relight
from relightanyone.model.networks.stage2 import Stage2Model, texel_mesh_normals
from relightanyone.model.train.checkpoint import read_plain_torch_file, save_checkpoint
from relightanyone.render.envmap import PrefilteredEnvmap, envmap_to_sh, load_envmap, prefilter_envmap
from relightanyone.render.lights import DirectionalLights, PointLights
from relightanyone.render.rasterize import rasterize
from relightanyone.render.sh import project_directions_to_sh
from relightanyone.render.shading import (
    combine_diffuse_specular,
    diffuse_color,
    reflected_view_directions,
    specular_directional_lights,
    specular_envmap,
)

AVATAR_FORMAT = "relightanyone-avatar"
AVATAR_VERSION = 1
GAUSSIAN_FIELDS = ("means", "quats", "scales", "opacities", "colours")
BINDING_FIELDS = ("valid_index", "texel_faces", "texel_barycentrics", "faces")
ENVMAP_LEVELS = 4
ENVMAP_MAX_BASE_HEIGHT = 256

Lighting = PointLights | DirectionalLights | PrefilteredEnvmap | torch.Tensor | str | Path


def prefilter_for_shading(env: torch.Tensor) -> PrefilteredEnvmap:
    """The specular mip chain of a ``(3, H, W)`` map at about its own resolution (16 to 256 rows)."""

    smallest = 2 << (ENVMAP_LEVELS - 1)  # the coarsest level keeps at least 2 rows
    base = min(max(1 << int(env.shape[1] - 1).bit_length(), smallest), ENVMAP_MAX_BASE_HEIGHT)
    return prefilter_envmap(env, num_levels=ENVMAP_LEVELS, base_height=base)


def resolve_lighting(lighting: Lighting) -> PointLights | DirectionalLights | PrefilteredEnvmap:
    """Lights stay as they are; an environment (tensor or file path) becomes its prefiltered mip chain."""
    if isinstance(lighting, (PointLights, DirectionalLights, PrefilteredEnvmap)):
        return lighting
    if isinstance(lighting, (str, Path)):
        return prefilter_for_shading(load_envmap(lighting))
    if isinstance(lighting, torch.Tensor):
        if lighting.ndim != 3 or lighting.shape[0] != 3:
            raise ValueError(
                f"an environment map must be a (3, H, W) lat-long tensor, got {tuple(lighting.shape)}"
            )
        return prefilter_for_shading(lighting.float())
    raise TypeError(
        f"lighting must be PointLights, DirectionalLights, an environment map (tensor, PrefilteredEnvmap or "
        f".exr/.hdr path), got {type(lighting).__name__}"
    )


def shade_reflectance(
    params: RelightParams,
    positions: torch.Tensor,
    camera_positions: torch.Tensor,
    lighting: PointLights | DirectionalLights | PrefilteredEnvmap,
    head_centre: torch.Tensor,
    normalization: str = "rgca",
    inverse_square: bool = True,
) -> torch.Tensor:
    """RGCA colour of every Gaussian seen from each camera under any lighting.

    Args:
        params: reflectance of C views (B = C) of N Gaussians.
        positions: (C, N, 3) Gaussian centres; camera_positions: (C, 3); head_centre: (3,).
        lighting: resolved lighting (see :func:`resolve_lighting`), shared by all views.
    Returns:
        (C, N, 3) linear RGB.
    """

    views = positions.shape[0]
    if isinstance(lighting, PointLights):
        lights = lighting.to(positions.device, positions.dtype)
        return relight(
            params,
            positions,
            camera_positions,
            lights.positions.expand(views, -1, -1),
            lights.intensities.expand(views, -1, -1),
            head_centre,
            normalization,
            inverse_square,
        ).colour
    lobes = reflected_view_directions(positions, camera_positions, params.normals)
    if isinstance(lighting, DirectionalLights):
        lights = lighting.to(positions.device, positions.dtype)
        light_sh = project_directions_to_sh(lights.directions, lights.irradiance, params.sh_order)
        specular = specular_directional_lights(
            lobes,
            params.roughness,
            lights.directions.expand(views, -1, -1),
            lights.irradiance.expand(views, -1, -1),
            params.visibility,
            normalization=normalization,
        )
    else:
        light_sh = envmap_to_sh(lighting.levels[0].to(positions.device, positions.dtype), params.sh_order)
        specular = specular_envmap(
            lobes, params.roughness, lighting, params.visibility, normalization=normalization
        )
    diffuse = diffuse_color(params.albedo, params.transfer, light_sh.expand(views, -1, -1))
    return combine_diffuse_specular(diffuse, specular)


@torch.no_grad()
def relight_views(
    avatar,
    w2c: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    lightings: list[Lighting],
    lightings_per_pass: int = 8,
    background: torch.Tensor | None = None,
) -> torch.Tensor:
    """Render an avatar in C pinhole views under P lightings: (P, C, 3, H, W) linear RGB.

    ``avatar`` is a :class:`FittedAvatar` or anything with its Gaussian tensors, ``reflectance(camera
    positions)``, ``head_centre`` and ``stage2_preset`` (the evaluation's single-stage avatar).

    The stage-2 reflectance is evaluated once per view and shared by every lighting; up to
    ``lightings_per_pass`` lightings are splatted in one rasterizer call as stacked colour channels (the
    geometry, and so the sorting and blending weights, is the same for all of them).

    Args:
        w2c: (C, 4, 4); K: (C, 3, 3), on the avatar's device or movable there.
        lightings: see the module docstring; resolved once each.
        background: optional (3,) linear RGB; black by default.
    """

    if lightings_per_pass < 1:
        raise ValueError(f"lightings_per_pass must be >= 1, got {lightings_per_pass}")
    device = avatar.means.device
    w2c, K = w2c.to(device, torch.float32), K.to(device, torch.float32)
    centres = camera_centres(w2c)
    views = centres.shape[0]
    params = avatar.reflectance(centres)
    positions = avatar.means.expand(views, -1, -1)
    resolved = [resolve_lighting(lighting) for lighting in lightings]
    passes = []
    for first in range(0, len(resolved), lightings_per_pass):
        group = resolved[first : first + lightings_per_pass]
        colours = [
            shade_reflectance(
                params,
                positions,
                centres,
                lighting,
                avatar.head_centre,
                avatar.stage2_preset.lobe_normalization,
                avatar.stage2_preset.inverse_square,
            )
            for lighting in group
        ]
        fill = None if background is None else background.to(device, torch.float32).repeat(len(group))
        image, _, _ = rasterize(
            avatar.means,
            avatar.quats,
            avatar.scales,
            avatar.opacities,
            torch.cat(colours, dim=-1),
            w2c,
            K,
            width,
            height,
            background=fill,
        )
        passes.append(image.reshape(views, len(group), 3, height, width).transpose(0, 1))
    return torch.cat(passes)


def check_pinhole_cameras(cameras) -> tuple[int, int]:
    """(width, height) shared by a :class:`~relightanyone.render.camera.Cameras` batch without distortion."""
    if len(cameras) == 0:
        raise ValueError("relight needs at least one camera")
    if bool((cameras.dist != 0).any()):
        raise ValueError(
            "relight renders pinhole cameras: undistort the images and pass cameras with zero distortion"
        )
    sizes = {(int(w), int(h)) for w, h in zip(cameras.width.tolist(), cameras.height.tolist(), strict=True)}
    if len(sizes) != 1:
        raise ValueError(f"relight renders one image size per call; these cameras have sizes {sorted(sizes)}")
    return sizes.pop()


@dataclass
class FittedAvatar:
    """One fitted subject, ready to relight. Tensors are float32 on the CPU unless moved.

    Attributes:
        means (N, 3) metres; quats (N, 4) unit w x y z; scales (N, 3) metres; opacities (N,);
        colours (N, 3) full-on colours (the stage-2 input, not a relit colour).
        vertices: (V, 3) the fitted model's decoded mesh. tracked_vertices: (V, 3) input tracked mesh or None.
        binding: the valid UV texels (one per Gaussian, in the same order).
        stage2: the frozen stage-2 network (eval mode, no gradients).
        stage1_preset, stage2_preset: sizes and shading options (lobe normalisation, falloff).
        rig: the OLAT rig of the stage-2 dataset. scene_intensities: (L, 3) fitted input lighting per rig light.
        metadata: JSON-serializable facts about the fit.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colours: torch.Tensor
    vertices: torch.Tensor
    tracked_vertices: torch.Tensor | None
    binding: TexelBinding
    stage2: Stage2Model
    stage1_preset: Stage1Preset
    stage2_preset: Stage2Preset
    rig: PointLights
    scene_intensities: torch.Tensor
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        count = self.binding.count
        for name in GAUSSIAN_FIELDS:
            value = getattr(self, name)
            if value.shape[0] != count:
                raise ValueError(
                    f"avatar {name} has {value.shape[0]} rows but the UV binding has {count} Gaussians"
                )
        if self.scene_intensities.shape != (len(self.rig), 3):
            raise ValueError(
                f"scene_intensities must be ({len(self.rig)}, 3), got {tuple(self.scene_intensities.shape)}"
            )
        self.stage2.eval().requires_grad_(False)

    @property
    def head_centre(self) -> torch.Tensor:
        """(3,) canonical metres: the origin of the light SH and of the view directions."""
        return self.stage2.head_centre

    @property
    def gaussian_count(self) -> int:
        return self.binding.count

    def olat(self, index: int) -> PointLights:
        """Rig light ``index`` alone, at its calibrated intensity."""
        return self.rig.olat(index)

    def scene_lights(self) -> PointLights:
        """The rig with the fitted intensities: the lighting of the images the avatar was fitted to."""
        return PointLights(self.rig.positions, self.scene_intensities)

    def reflectance(self, camera_positions: torch.Tensor) -> RelightParams:
        """Stage-2 reflectance seen from C camera centres (C, 3) -> RelightParams with B = C."""
        views = camera_positions.shape[0]
        normals = texel_mesh_normals(self.vertices[None], self.binding).expand(views, -1, -1)
        return self.stage2(
            self.colours.expand(views, -1, -1), self.means.expand(views, -1, -1), normals, camera_positions
        )

    @torch.no_grad()
    def relit_colours(self, camera_positions: torch.Tensor, lighting: Lighting) -> torch.Tensor:
        """(C, 3) camera centres -> (C, N, 3) relit colour of every Gaussian."""
        camera_positions = torch.as_tensor(camera_positions, dtype=torch.float32).reshape(-1, 3)
        views = camera_positions.shape[0]
        return shade_reflectance(
            self.reflectance(camera_positions),
            self.means.expand(views, -1, -1),
            camera_positions,
            resolve_lighting(lighting),
            self.head_centre,
            self.stage2_preset.lobe_normalization,
            self.stage2_preset.inverse_square,
        )

    def gaussians(self, lighting: Lighting, view) -> dict[str, torch.Tensor]:
        """Per-Gaussian tensors of the avatar relit for one view (e.g. for a PLY export).

        Args:
            lighting: see the module docstring.
            view: a camera centre (3,) in canonical metres, or a one-camera ``Cameras``.
        Returns:
            means (N, 3), quats (N, 4), scales (N, 3), opacities (N,), colours (N, 3) linear RGB.
        """
        if hasattr(view, "w2c"):
            if view.w2c.shape[0] != 1:
                raise ValueError(
                    f"gaussians() relights for one view; got {view.w2c.shape[0]} cameras (index one: cameras[i])"
                )
            position = camera_centres(view.w2c.float())[0]
        else:
            position = torch.as_tensor(view, dtype=torch.float32)
        if position.shape != (3,):
            raise ValueError(
                f"view must be one camera centre (3,) or one camera, got shape {tuple(position.shape)}"
            )
        colours = self.relit_colours(position[None], lighting)[0]
        return {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "colours": colours,
        }

    @torch.no_grad()
    def relight(self, cameras, lighting: Lighting, background: torch.Tensor | None = None) -> torch.Tensor:
        """Render the avatar into cameras under a lighting.

        Args:
            cameras: :class:`~relightanyone.render.camera.Cameras` (C cameras of one size, no distortion).
            lighting: see the module docstring.
            background: optional (3,) linear RGB; black by default.
        Returns:
            (C, 3, H, W) linear RGB.
        """

        width, height = check_pinhole_cameras(cameras)
        w2c, K = cameras.w2c.float(), cameras.K.float()
        colours = self.relit_colours(camera_centres(w2c), lighting)
        image, _, _ = rasterize(
            self.means,
            self.quats,
            self.scales,
            self.opacities,
            colours,
            w2c,
            K,
            width,
            height,
            background=background,
        )
        return image

    def save(self, path: str | Path) -> Path:
        """Write the avatar to one file (atomic: temporary file, fsync, rename)."""

        path = Path(path)
        payload = {
            "format": AVATAR_FORMAT,
            "version": AVATAR_VERSION,
            "metadata_json": json.dumps(self.metadata, sort_keys=True),
            "stage1_preset_json": json.dumps(self.stage1_preset.to_json(), sort_keys=True),
            "stage2_preset_json": json.dumps(self.stage2_preset.to_json(), sort_keys=True),
            "gaussians": {name: getattr(self, name).detach().cpu().contiguous() for name in GAUSSIAN_FIELDS},
            "vertices": self.vertices.detach().cpu(),
            "tracked_vertices": None
            if self.tracked_vertices is None
            else self.tracked_vertices.detach().cpu(),
            "binding": {name: getattr(self.binding, name).cpu() for name in BINDING_FIELDS},
            "uv_size": int(self.binding.uv_size),
            "stage2": {name: value.cpu() for name, value in self.stage2.state_dict().items()},
            "stage2_radius": float(self.stage2.radius),
            "rig": {"positions": self.rig.positions.cpu(), "intensities": self.rig.intensities.cpu()},
            "scene_intensities": self.scene_intensities.detach().cpu(),
        }
        save_checkpoint(path, payload)
        return path

    @classmethod
    def load(cls, path: str | Path) -> FittedAvatar:
        """Read a file written by :meth:`save`; errors name the file and what is wrong."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: no avatar file; fit one first (relightanyone.model.fit.fitter.fit_subject)"
            )
        payload = read_plain_torch_file(path, "fitted avatar file", "fit the subject again")
        if not isinstance(payload, dict) or payload.get("format") != AVATAR_FORMAT:
            raise InputError(
                f"{path}: field 'format' is not {AVATAR_FORMAT!r}; this is not a fitted avatar file"
            )
        if payload.get("version") != AVATAR_VERSION:
            raise InputError(
                f"{path}: avatar version {payload.get('version')!r}, this toolkit reads {AVATAR_VERSION}"
            )
        try:
            stage1_preset = Stage1Preset.from_json(json.loads(payload["stage1_preset_json"]))
            stage2_preset = Stage2Preset.from_json(json.loads(payload["stage2_preset_json"]))
            binding = TexelBinding(**payload["binding"], uv_size=int(payload["uv_size"]))
            stage2_state = payload["stage2"]
            stage2 = Stage2Model(
                binding,
                stage2_state["head_centre"],
                payload["stage2_radius"],
                stage2_preset.sh_order,
                stage2_preset.base_channels,
                stage2_preset.max_channels,
            )
            stage2.load_state_dict(stage2_state)
            rig = PointLights(payload["rig"]["positions"], payload["rig"]["intensities"])
            return cls(
                **payload["gaussians"],
                vertices=payload["vertices"],
                tracked_vertices=payload["tracked_vertices"],
                binding=binding,
                stage2=stage2,
                stage1_preset=stage1_preset,
                stage2_preset=stage2_preset,
                rig=rig,
                scene_intensities=payload["scene_intensities"],
                metadata=json.loads(payload["metadata_json"]),
            )
        except (KeyError, TypeError, RuntimeError) as error:
            raise InputError(f"{path}: avatar file is incomplete or inconsistent ({error!r})") from error

    def to(self, device: torch.device | str) -> FittedAvatar:
        """A copy with every tensor (and the stage-2 network) on ``device``."""
        moved = {
            name: getattr(self, name).to(device)
            for name in (*GAUSSIAN_FIELDS, "vertices", "scene_intensities")
        }
        tracked = None if self.tracked_vertices is None else self.tracked_vertices.to(device)
        binding = TexelBinding(
            **{n: getattr(self.binding, n).to(device) for n in BINDING_FIELDS}, uv_size=self.binding.uv_size
        )
        stage2 = Stage2Model(
            binding,
            self.head_centre,
            self.stage2.radius,
            self.stage2_preset.sh_order,
            self.stage2_preset.base_channels,
            self.stage2_preset.max_channels,
        )
        stage2.load_state_dict(self.stage2.state_dict())
        return dataclasses.replace(
            self,
            **moved,
            tracked_vertices=tracked,
            binding=binding,
            stage2=stage2.to(device),
            rig=self.rig.to(device),
        )


def decoded_avatar(model, subject_index: int, tracked_vertices: torch.Tensor | None, metadata: dict):
    """The :class:`FittedAvatar` of stage-1 training subject ``subject_index``, decoded without fitting.

    Its Gaussians are decoded with ``model.lighting_code``: the OLAT dataset's code (the method: colours
    as stage 2 was trained on them), or any other code (the lighting-code ablation of the evaluation).

    Args:
        model: :class:`~relightanyone.model.fit.fitter.RelightableModel` (stage 1, stage 2, the OLAT rig).
        subject_index: row of ``model.stage1.identity_codes``.
        tracked_vertices: (V, 3) tracked mesh of the rendered frame, or None.
    Returns:
        the avatar; its scene lighting is the calibrated rig (the OLAT dataset's full-on light).
    """

    stage1 = model.stage1
    if not 0 <= subject_index < stage1.identity_codes.shape[0]:
        raise ValueError(
            f"subject index {subject_index} is outside the stage-1 run's {stage1.identity_codes.shape[0]} codes"
        )
    with torch.no_grad():
        z_id = stage1.identity_codes[subject_index : subject_index + 1].detach()
        vertices, gaussians = stage1.decode(z_id, model.lighting_code.reshape(1, -1))
    return avatar_from_decoded(
        vertices,
        gaussians,
        tracked_vertices,
        stage1,
        model.stage2,
        model,
        (model.full_on_rig or model.rig).intensities,
        {"mesh": "decoded", "olat_dataset": model.olat_dataset, **model.sources, **metadata},
    )


def avatar_from_decoded(
    vertices, gaussians, tracked_vertices, stage1, stage2, model, scene_intensities, metadata
) -> FittedAvatar:
    """A :class:`FittedAvatar` holding copies of one decoded sample: vertices (1, V, 3) and Gaussians
    (batch 1) of ``stage1``, a copy of ``stage2``, the rig of ``model`` and the (L, 3) scene intensities."""
    return FittedAvatar(
        means=gaussians.means[0].clone(),
        quats=gaussians.quats[0].clone(),
        scales=gaussians.scales[0].clone(),
        opacities=gaussians.opacities[0].clone(),
        colours=gaussians.colours[0].clone(),
        vertices=vertices[0].clone(),
        tracked_vertices=None if tracked_vertices is None else tracked_vertices.clone(),
        binding=stage1.binding,
        stage2=copy.deepcopy(stage2),
        stage1_preset=stage1.preset,
        stage2_preset=model.stage2_preset,
        rig=model.rig,
        scene_intensities=scene_intensities.detach().clone(),
        metadata=metadata,
    )
