"""Cameras, frames and files for relighting and exporting fitted avatars.

What the ``relight`` and ``export`` commands (:mod:`relightanyone.model.fit.relight`) are made of:

* cameras: the dataset rows the avatar was fitted from, any subject of a normalized dataset, or an orbit
  around the head centre (:func:`orbit_cameras_around`);
* frames: every camera under every lighting (:mod:`relightanyone.model.fit.lighting_choice`);
* outputs: sRGB PNG frames (optional linear EXR), a contact sheet, an animated strip (WebP, GIF or MP4),
  and the 3DGS PLY export (:mod:`relightanyone.model.fit.ply`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from relightanyone.align.colour import linear_to_display, linear_to_srgb
from relightanyone.errors import InputError
from relightanyone.format.preview import render_contact_sheet
from relightanyone.format.reader import NormalizedDataset
from relightanyone.model.fit.avatar import (
    FittedAvatar,
    check_pinhole_cameras,
    relight_views,
)
from relightanyone.model.fit.lighting_choice import NamedLighting, safe_name
from relightanyone.model.networks.render import orbit_cameras
from relightanyone.progress import progress_bar
from relightanyone.render.camera import Cameras
from relightanyone.render.envmap import PrefilteredEnvmap, save_envmap

ORBIT_ELEVATION_DEG = 10.0
ORBIT_DISTANCE_RADII = 6.0  # camera distance in head radii: a portrait-lens perspective
ORBIT_FILL = 0.36  # the head's radius covers this fraction of the image side
HEAD_OPACITY = 0.1  # Gaussians at least this opaque define the head's extent
HEAD_QUANTILE = 0.99  # stray Gaussians beyond this quantile of distances do not widen the framing
LIGHTINGS_PER_PASS = 8  # relit colour sets splatted together: 3 channels each, bounded memory
AUTO_EXPOSURE_TARGET = 0.9  # auto exposure maps the 99th percentile of lit pixels to this value


def head_extent(avatar: FittedAvatar) -> tuple[torch.Tensor, float]:
    """(centre (3,), radius m) of the avatar: its head centre and the distance that holds its opaque Gaussians."""
    centre = avatar.head_centre.detach().float().cpu()
    means = avatar.means.detach().float().cpu()
    opaque = avatar.opacities.detach().cpu() >= HEAD_OPACITY
    points = means[opaque] if bool(opaque.any()) else means
    distances = (points - centre).norm(dim=1)
    radius = float(torch.quantile(distances, HEAD_QUANTILE)) if len(distances) else 0.0
    if not radius > 0:
        raise InputError("the avatar has no Gaussians away from its head centre; cannot frame it")
    return centre, radius


def frontal_view(avatar: FittedAvatar, distance: float | None = None) -> torch.Tensor:
    """(3,) camera centre in front of the face (+z of canonical space) at ``distance`` metres from the centre."""
    centre, radius = head_extent(avatar)
    distance = ORBIT_DISTANCE_RADII * radius if distance is None else float(distance)
    return centre + torch.tensor([0.0, 0.0, distance])


def orbit_cameras_around(
    avatar: FittedAvatar,
    count: int,
    size: int,
    distance: float | None = None,
    elevation_deg: float = ORBIT_ELEVATION_DEG,
) -> Cameras:
    """``count`` square ``size``² pinhole cameras on a circle around the head centre, the first one frontal.

    The distance defaults to ``ORBIT_DISTANCE_RADII`` head radii; the focal length makes the head's radius
    cover ``ORBIT_FILL`` of the image side. Names are ``orbit000`` ...
    """

    if count < 1 or size < 2:
        raise InputError(f"an orbit needs --count >= 1 and --size >= 2, got {count} and {size}")
    centre, radius = head_extent(avatar)
    distance = ORBIT_DISTANCE_RADII * radius if distance is None else float(distance)
    if distance <= radius:
        raise InputError(f"orbit distance {distance:.3f} m is inside the head (radius {radius:.3f} m)")
    # A sphere of radius r at distance d projects to a disc of radius f r / sqrt(d² - r²).
    focal = ORBIT_FILL * size * math.sqrt(distance**2 - radius**2) / radius
    K = np.array([[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]])
    Ks, w2cs = orbit_cameras(count, distance, centre.double().numpy(), K, elevation_deg)
    return Cameras.create(
        torch.from_numpy(Ks),
        torch.from_numpy(w2cs),
        size,
        size,
        names=[f"orbit{i:03d}" for i in range(count)],
    )


def dataset_cameras(
    dataset_dir: Path, subject: str | None = None, keys: Sequence[str] | None = None
) -> Cameras:
    """Cameras of image rows of a normalized dataset, named by camera.

    With ``keys``: exactly those rows. Otherwise the rows of ``subject``'s first frame (full-on rows when
    it has any). Only cameras of the first row's image size are kept (one render size per call).
    """

    dataset = NormalizedDataset(dataset_dir)
    if keys is not None:
        missing = [k for k in keys if k not in dataset]
        if missing:
            raise InputError(
                f"{dataset.path}: no image rows {missing[:4]}; was the dataset rewritten since the fit?"
            )
        rows = [dataset.row(k) for k in keys]
    else:
        if subject not in dataset.subjects:
            raise InputError(
                f"{dataset.path}: no subject {subject!r}; it has {', '.join(dataset.subjects[:12])}"
            )
        selected = dataset.select(subjects=subject, patterns="full") or dataset.select(subjects=subject)
        # Keys are <dataset>/<subject>/<frame>/<camera>/<pattern>: the frame is known without reading rows.
        first = min(int(key.split("/")[2]) for key in selected)
        rows = [dataset.row(k) for k in dataset.select(subjects=subject, frames=first)]
        full = [r for r in rows if r.pattern == "full"]
        rows = full or [r for r in rows if r.pattern == rows[0].pattern]
        by_camera = {}
        for row in rows:
            by_camera.setdefault(row.camera, row)
        rows = list(by_camera.values())
    width, height = rows[0].width, rows[0].height
    rows = [r for r in rows if (r.width, r.height) == (width, height)]
    return Cameras.create(
        torch.tensor(np.stack([r.K for r in rows])),
        torch.tensor(np.stack([r.w2c for r in rows])),
        width,
        height,
        names=[r.camera for r in rows],
    )


def fitted_cameras(avatar: FittedAvatar, source: str | Path | None = None) -> Cameras:
    """Cameras of the rows the avatar was fitted from (its metadata's ``data`` folder and ``keys``)."""
    metadata = avatar.metadata
    data = metadata.get("data")
    keys = metadata.get("keys")
    where = f"{source}: " if source else ""
    if not data or not keys:
        raise InputError(
            f"{where}the avatar's metadata does not name the dataset it was fitted from "
            "('data' and 'keys'); pass --data DIR --subject S to take cameras from a dataset"
        )
    if not Path(data).is_dir():
        raise InputError(
            f"{where}the avatar was fitted from {data}, which is not there any more; "
            "pass --data DIR --subject S to take cameras from a dataset"
        )
    return dataset_cameras(Path(data), keys=keys)


def lighting_to(lighting, device: torch.device | str):
    """A resolved lighting (point, directional or prefiltered map) with its tensors on ``device``."""
    if isinstance(lighting, PrefilteredEnvmap):
        return PrefilteredEnvmap(tuple(level.to(device) for level in lighting.levels), lighting.sigma_step)
    return lighting.to(device)


def render_frames(
    avatar: FittedAvatar,
    cameras: Cameras,
    lightings: Sequence[NamedLighting],
    background: torch.Tensor | None = None,
    progress: bool = True,
    lightings_per_pass: int = LIGHTINGS_PER_PASS,
) -> Iterator[tuple[str, str, torch.Tensor]]:
    """Relight the avatar in every camera under every lighting, camera-major (same images as
    :meth:`FittedAvatar.relight`).

    Per camera, up to ``lightings_per_pass`` lightings share one stage-2 evaluation and one splat as stacked
    feature channels (:func:`relightanyone.model.fit.avatar.relight_views`).

    Args:
        cameras: C pinhole cameras of one size. background: (3,) linear RGB or None (black).
    Yields:
        ``(camera name, lighting label, image (3, H, W) linear RGB)``, one frame at a time.
    """
    width, height = check_pinhole_cameras(cameras)
    names = cameras.names or tuple(f"cam{i:03d}" for i in range(len(cameras)))
    device = avatar.means.device
    lightings = [NamedLighting(named.label, lighting_to(named.lighting, device)) for named in lightings]
    bar = progress_bar(
        total=len(cameras) * len(lightings), desc="relight", unit="frame", disable=not progress
    )
    with bar, torch.no_grad():
        for index, name in enumerate(names):
            w2c = cameras.w2c[index : index + 1].to(device, torch.float32)
            K = cameras.K[index : index + 1].to(device, torch.float32)
            for first in range(0, len(lightings), lightings_per_pass):
                chunk = lightings[first : first + lightings_per_pass]
                stacked = relight_views(
                    avatar, w2c, K, width, height, [named.lighting for named in chunk], len(chunk), background
                )
                for offset, named in enumerate(chunk):
                    bar.update(1)
                    yield name, named.label, stacked[offset, 0].cpu()


def exposure_gain(images: Sequence[torch.Tensor], stops: float | None) -> float:
    """Linear gain of an exposure: ``2 ** stops``, or (``None``) auto: the 99th percentile of the lit pixels
    of all ``images`` (each (3, H, W)) maps to ``AUTO_EXPOSURE_TARGET`` (one gain for all, so nothing flickers)."""
    if stops is not None:
        return float(2.0**stops)
    lit = torch.cat([image.amax(dim=0).reshape(-1) for image in images])
    lit = lit[lit > 1e-4]
    if lit.numel() == 0:
        return 1.0
    reference = float(torch.quantile(lit.double(), 0.99))
    return AUTO_EXPOSURE_TARGET / reference if reference > 0 else 1.0


def write_exr(path: Path, image: torch.Tensor) -> None:
    """(3, H, W) linear RGB -> float32 EXR."""

    save_envmap(path, image)


@dataclass
class SavedFrames:
    """What :func:`save_frames` wrote: (camera, lighting) per frame, its sRGB uint8 image, the files, the gain."""

    frames: list[tuple[str, str]] = field(default_factory=list)
    encoded: list[np.ndarray] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    gain: float = 1.0


def save_frames(
    frames: Iterable[tuple[str, str, torch.Tensor]], out: Path, stops: float | None, exr: bool = False
) -> SavedFrames:
    """Write ``<camera>_<lighting>.png`` (sRGB) and, with ``exr``, ``.exr`` (linear) for every frame.

    A fixed exposure (``stops``) streams the frames, keeping only their 8-bit encodings; auto exposure
    (``None``) needs every linear frame before the first PNG, so it holds them all in memory.
    """
    from PIL import Image

    saved = SavedFrames()
    if stops is None:
        frames = list(frames)
        saved.gain = exposure_gain([image for _, _, image in frames], None)
    else:
        saved.gain = exposure_gain([], stops)
    for camera, label, image in frames:
        stem = f"{safe_name(camera)}_{label}"
        display = linear_to_display(image, saved.gain).transpose(1, 2, 0)
        Image.fromarray(display).save(out / f"{stem}.png")
        saved.files.append(f"{stem}.png")
        if exr:
            write_exr(out / f"{stem}.exr", image)
            saved.files.append(f"{stem}.exr")
        saved.frames.append((camera, label))
        saved.encoded.append(display)
    return saved


def write_strip(path: Path, frames: Sequence[np.ndarray], fps: float = 12.0) -> Path:
    """An animation of (H, W, 3) uint8 frames: ``.webp`` (lossless) or ``.gif`` via Pillow, ``.mp4`` via PyAV."""
    if not frames:
        raise ValueError("an animated strip needs at least one frame")
    if fps <= 0:
        raise InputError(f"--fps must be positive, got {fps}")
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".webp", ".gif"):
        from PIL import Image

        images = [Image.fromarray(frame) for frame in frames]
        options = {"lossless": True, "quality": 100} if suffix == ".webp" else {"disposal": 2}
        images[0].save(
            path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0, **options
        )
    elif suffix == ".mp4":
        write_mp4(path, frames, fps)
    else:
        raise ValueError(f"{path}: unsupported animation format {suffix!r} (use .webp, .gif or .mp4)")
    return path


def write_mp4(path: Path, frames: Sequence[np.ndarray], fps: float) -> None:
    """H.264 MP4 via PyAV; odd frame sizes are padded by one black row/column (yuv420p needs even sizes)."""
    from fractions import Fraction

    import av

    height, width = frames[0].shape[:2]
    even_h, even_w = height + height % 2, width + width % 2
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height, stream.pix_fmt = even_w, even_h, "yuv420p"
        for frame in frames:
            padded = np.zeros((even_h, even_w, 3), np.uint8)
            padded[:height, :width] = frame
            for packet in stream.encode(av.VideoFrame.from_ndarray(padded, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def contact_sheet(
    frames: Sequence[np.ndarray], labels: Sequence[str], columns: int | None = None
) -> np.ndarray:
    """Labelled grid of (H, W, 3) uint8 frames -> one uint8 image (tiles at most 256 px)."""

    tile = min(256, max(max(frame.shape[:2]) for frame in frames))
    return render_contact_sheet(list(frames), [None] * len(frames), list(labels), tile=tile, columns=columns)


def export_gaussians(
    avatar: FittedAvatar,
    lighting,
    view: torch.Tensor,
    colour_space: str = "srgb",
    gain: float = 1.0,
) -> dict[str, torch.Tensor]:
    """The avatar's Gaussians relit for one view (3,), colours encoded for a splat viewer.

    ``colour_space="srgb"``: linear colours × gain, clipped to [0, 1] and sRGB-encoded (what viewers show
    as is). ``"linear"``: linear colours × gain, unclipped. Returns means, quats, scales, opacities, colours.
    """

    if colour_space not in ("srgb", "linear"):
        raise ValueError(f"colour space must be 'srgb' or 'linear', got {colour_space!r}")
    device = avatar.means.device
    gaussians = avatar.gaussians(lighting_to(lighting, device), view.to(device))
    gaussians = {name: value.detach().cpu() for name, value in gaussians.items()}
    colours = gaussians["colours"] * gain
    if colour_space == "srgb":
        colours = linear_to_srgb(colours.clamp(0.0, 1.0)).clamp(0.0, 1.0)
    return {**gaussians, "colours": colours}
