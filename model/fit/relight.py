"""What ``relightanyone relight`` and ``relightanyone export`` do with a fitted avatar.

``relight`` renders the avatar in chosen cameras under chosen lightings
(:mod:`relightanyone.model.fit.lighting_choice`) into sRGB PNG frames, a contact sheet, animated strips
and ``relight.json``; ``export`` writes it relit under one lighting as a 3D Gaussian Splatting PLY.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.model.device import resolve_device
from relightanyone.model.fit.avatar import FittedAvatar
from relightanyone.model.fit.avatar_tools import (
    contact_sheet,
    dataset_cameras,
    export_gaussians,
    fitted_cameras,
    frontal_view,
    orbit_cameras_around,
    render_frames,
    save_frames,
    write_strip,
)
from relightanyone.model.fit.lighting_choice import NamedLighting, safe_name
from relightanyone.model.fit.ply import write_gaussian_ply
from relightanyone.render.camera import Cameras

RELIGHT_REPORT = "relight.json"
CONTACT_SHEET = "contact_sheet.png"


def load_avatar(path: Path, device: str = "cpu") -> tuple[FittedAvatar, Path]:
    """The avatar at ``path`` on ``device`` ("auto": CUDA when available), and the file it was read from.

    ``path`` may be a folder of avatars (what ``relightanyone fit`` writes): its first ``*.avatar`` in name
    order is used, so a pipeline can name the fit's output folder without knowing subject names.
    """
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.avatar"))
        if not found:
            raise InputError(f"{path}: folder holds no *.avatar file; fit one first")
        path = found[0]
    avatar = FittedAvatar.load(path)
    target = resolve_device(device)
    return (avatar if target.type == "cpu" else avatar.to(target)), path


@dataclass(frozen=True)
class CameraChoice:
    """Where relit frames are seen from.

    ``source="dataset"``: the rows the avatar was fitted from, or with ``data`` and ``subject`` the first
    frame's cameras of that subject in that dataset, scaled by ``image_scale``. ``source="orbit"``:
    ``count`` square cameras of ``size`` pixels around the head at ``distance`` metres (default: 6 head
    radii).
    """

    source: str = "dataset"
    data: Path | None = None
    subject: str | None = None
    count: int = 24
    size: int = 512
    distance: float | None = None
    image_scale: float = 1.0

    def check(self) -> None:
        """Raise InputError for options that do not go together (checked before the avatar is loaded)."""
        if (self.data is None) != (self.subject is None):
            raise InputError("--data and --subject go together (cameras of that subject in that dataset)")
        if self.data is not None and self.source != "dataset":
            raise InputError("--data/--subject choose dataset cameras; drop them or use --cameras dataset")
        if self.image_scale <= 0:
            raise InputError(f"--image-scale must be positive, got {self.image_scale}")


def chosen_cameras(avatar: FittedAvatar, avatar_file: Path, choice: CameraChoice) -> Cameras:
    """The cameras ``choice`` asks for (:class:`CameraChoice`)."""
    choice.check()
    if choice.source == "orbit":
        return orbit_cameras_around(avatar, choice.count, choice.size, choice.distance)
    if choice.data is not None:
        if not Path(choice.data).is_dir():
            raise InputError(f"{choice.data}: not a normalized dataset folder (--data)")
        cameras = dataset_cameras(choice.data, subject=choice.subject)
    else:
        cameras = fitted_cameras(avatar, avatar_file)
    return cameras.resize(choice.image_scale) if choice.image_scale != 1.0 else cameras


def relight_into(
    avatar: FittedAvatar,
    avatar_path: Path,
    cameras: Cameras,
    lightings: Sequence[NamedLighting],
    out: Path,
    stops: float | None = 0.0,
    exr: bool = False,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    strip_format: str = "webp",
    fps: float = 12.0,
    orbit: bool = False,
    progress: bool = True,
) -> dict:
    """Relight ``avatar`` in every camera under every lighting into the folder ``out``.

    Writes ``<camera>_<lighting>.png`` (sRGB after ``stops`` of exposure, None: auto) and with ``exr`` the
    linear ``.exr``, ``contact_sheet.png`` (one column per lighting when there are several), an animation
    per camera of a turning environment map or, for an ``orbit`` under one lighting, one animation around the
    head (``strip_format`` "webp", "gif", "mp4" or "none"), and ``relight.json`` (naming ``avatar_path``,
    the avatar as given), which it returns.
    """
    from PIL import Image

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    background_rgb = torch.tensor(list(background), dtype=torch.float32)
    saved = save_frames(render_frames(avatar, cameras, lightings, background_rgb, progress), out, stops, exr)
    labels = [f"{camera} {label}" for camera, label in saved.frames]
    columns = len(lightings) if len(lightings) > 1 else None
    Image.fromarray(contact_sheet(saved.encoded, labels, columns)).save(out / CONTACT_SHEET)
    names = list(dict.fromkeys(camera for camera, _ in saved.frames))
    strips = []
    if strip_format != "none":
        if len(lightings) > 1:  # a turning environment: one animation per camera
            for camera in names:
                sequence = [e for e, (c, _) in zip(saved.encoded, saved.frames, strict=True) if c == camera]
                path = out / f"strip_{safe_name(camera)}.{strip_format}"
                strips.append(write_strip(path, sequence, fps).name)
        elif orbit and len(names) > 1:
            strips.append(write_strip(out / f"strip.{strip_format}", saved.encoded, fps).name)
    report = {
        "avatar": str(avatar_path),
        "subject": avatar.metadata.get("subject"),
        "lightings": [named.label for named in lightings],
        "cameras": names,
        "exposure_stops": stops,
        "exposure_gain": saved.gain,
        "frames": saved.files,
        "contact_sheet": CONTACT_SHEET,
        "strips": strips,
    }
    (out / RELIGHT_REPORT).write_text(json.dumps(report, indent=2) + "\n")
    return report


def export_ply(
    avatar: FittedAvatar,
    lighting: NamedLighting,
    out: Path,
    view: Sequence[float] | None = None,
    colour_space: str = "srgb",
    exposure: float = 0.0,
    sh_degree: int = 3,
) -> torch.Tensor:
    """Write the avatar relit under ``lighting`` as a 3DGS PLY, view-dependent colours baked for the camera
    centre ``view`` (canonical metres; default: in front of the face); returns that centre (3,)."""
    position = frontal_view(avatar) if view is None else torch.tensor(list(view), dtype=torch.float32)
    gaussians = export_gaussians(avatar, lighting.lighting, position, colour_space, 2.0**exposure)
    write_gaussian_ply(out, sh_degree=sh_degree, **gaussians)
    return position
