"""The ``relight`` and ``export`` commands for fitted avatars (files written by ``fit``).

Both take the same lighting options (exactly one of them):

* ``--olat K``: light K of the avatar's OLAT rig at its calibrated intensity;
* ``--point-light x,y,z[,r,g,b]`` (repeatable): point lights in canonical metres, linear RGB radiant
  intensity (default: the rig's mean light);
* ``--envmap FILE.exr|.hdr``: an equirectangular environment (+y up, centre column in front of the face);
  ``relight`` adds ``--rotate N``: N frames with the map turned by 360°/N steps about the vertical axis;
* ``--fitted-lighting``: the lighting estimated from the fitting images.

Heavy imports happen inside the commands so ``relightanyone --help`` stays fast.
"""

from __future__ import annotations

import json
from pathlib import Path

import click


def lighting_options(function):
    """The shared lighting options of ``relight`` and ``export``."""
    options = [
        click.option("--olat", type=int, default=None, metavar="K", help="Light K of the avatar's OLAT rig."),
        click.option(
            "--point-light",
            "point_lights",
            multiple=True,
            metavar="X,Y,Z[,R,G,B]",
            help="A point light in canonical metres (repeatable); R,G,B linear intensity, default the rig's mean light.",
        ),
        click.option(
            "--envmap",
            type=click.Path(path_type=Path),
            default=None,
            help="Equirectangular environment map (.exr or .hdr, linear, +y up).",
        ),
        click.option(
            "--fitted-lighting",
            is_flag=True,
            help="The lighting estimated from the images the avatar was fitted to.",
        ),
    ]
    for option in reversed(options):
        function = option(function)
    return function


DEVICE_OPTION = click.option(
    "--device",
    default="auto",
    show_default=True,
    help="Torch device to relight on: auto (CUDA when available), cpu, cuda, cuda:1, ...",
)


def load_avatar(path: Path, device: str = "cpu"):
    """The avatar file on ``device`` ("auto": CUDA when available); click errors for bad files or devices.

    ``path`` may be a folder of avatars (what ``relightanyone fit`` writes): its first ``*.avatar`` in name
    order is used, so a pipeline can name the fit's output folder without knowing subject names.
    """
    import torch

    from relightanyone.model.fit.avatar import FittedAvatar

    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.avatar"))
        if not found:
            raise click.BadParameter(
                f"{path}: folder holds no *.avatar file; fit one first", param_hint="AVATAR"
            )
        click.echo(f"using {found[0]} (the first of {len(found)} avatar(s) in {path})", err=True)
        path = found[0]
    try:
        avatar = FittedAvatar.load(path)
    except (FileNotFoundError, ValueError) as error:
        raise click.BadParameter(str(error), param_hint="AVATAR") from error
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        target = torch.device(device)
    except RuntimeError as error:
        raise click.BadParameter(
            f"{device!r} is not a torch device ({error})", param_hint="--device"
        ) from error
    if target.type == "cuda" and not torch.cuda.is_available():
        raise click.BadParameter(
            "CUDA is not available on this machine; use --device cpu", param_hint="--device"
        )
    return avatar if target.type == "cpu" else avatar.to(target)


def check_one_lighting(olat, point_lights, envmap, fitted_lighting, rotate: int = 1) -> None:
    """Usage errors for zero or several lighting options (checked before the avatar is loaded)."""
    given = [
        name
        for name, value in (
            ("--olat", olat is not None),
            ("--point-light", bool(point_lights)),
            ("--envmap", envmap is not None),
            ("--fitted-lighting", fitted_lighting),
        )
        if value
    ]
    if len(given) != 1:
        found = ", ".join(given) if given else "none"
        raise click.UsageError(
            f"give exactly one lighting: --olat, --point-light, --envmap or --fitted-lighting (got {found})"
        )
    if rotate != 1 and envmap is None:
        raise click.UsageError("--rotate turns an environment map: use it with --envmap")


def chosen_lightings(avatar, olat, point_lights, envmap, fitted_lighting, rotate: int = 1):
    """The lightings the options ask for, as ``NamedLighting`` objects; click errors for bad options."""
    from relightanyone.model.fit.avatar_tools import (
        NamedLighting,
        envmap_lightings,
        point_lights_from_specs,
        rig_mean_intensity,
    )

    check_one_lighting(olat, point_lights, envmap, fitted_lighting, rotate)
    if olat is not None:
        if not 0 <= olat < len(avatar.rig):
            raise click.BadParameter(
                f"the avatar's rig has {len(avatar.rig)} lights, so K must be in 0..{len(avatar.rig) - 1}; got {olat}",
                param_hint="--olat",
            )
        return [NamedLighting(f"olat-{olat:03d}", avatar.olat(olat))]
    if point_lights:
        try:
            lights = point_lights_from_specs(point_lights, rig_mean_intensity(avatar.rig))
        except ValueError as error:
            raise click.BadParameter(str(error), param_hint="--point-light") from error
        return [NamedLighting("point" if len(lights) == 1 else f"points{len(lights)}", lights)]
    if fitted_lighting:
        return [NamedLighting("fitted", avatar.scene_lights())]
    if not envmap.is_file():
        raise click.BadParameter(f"{envmap}: no such environment map file", param_hint="--envmap")
    try:
        return envmap_lightings(envmap, rotate)
    except ValueError as error:
        raise click.BadParameter(str(error), param_hint="--envmap") from error


def parse_exposure(text: str) -> float | None:
    """``auto`` -> None; a number of stops -> float."""
    if text.strip().lower() == "auto":
        return None
    try:
        return float(text)
    except ValueError as error:
        raise click.BadParameter(
            f"{text!r}: give a number of stops (e.g. 0, -1.5) or 'auto'", param_hint="--exposure"
        ) from error


@click.command("relight")
@click.argument("avatar", type=click.Path(path_type=Path))
@lighting_options
@click.option(
    "--rotate",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="With --envmap: N frames of the map turned about the vertical axis.",
)
@click.option(
    "--cameras",
    "camera_source",
    type=click.Choice(["dataset", "orbit"]),
    default="dataset",
    show_default=True,
    help="dataset: the fitted rows' cameras (or --data/--subject); orbit: around the head centre.",
)
@click.option(
    "--data",
    type=click.Path(path_type=Path),
    default=None,
    help="With --cameras dataset: take cameras from this normalized dataset instead.",
)
@click.option("--subject", default=None, help="With --data: the subject whose first frame's cameras to use.")
@click.option(
    "--count", type=click.IntRange(min=1), default=24, show_default=True, help="Orbit: number of cameras."
)
@click.option(
    "--size", type=click.IntRange(min=2), default=512, show_default=True, help="Orbit: image side in pixels."
)
@click.option(
    "--distance",
    type=float,
    default=None,
    help="Orbit: camera distance from the head centre in metres (default 6 head radii).",
)
@click.option(
    "--image-scale",
    type=float,
    default=1.0,
    show_default=True,
    help="Dataset cameras: render at this fraction of the stored size.",
)
@click.option(
    "--exposure",
    default="0",
    show_default=True,
    help="Exposure of the PNGs in stops (linear × 2^stops), or 'auto'.",
)
@click.option("--exr", is_flag=True, help="Also write every frame as a linear float32 EXR.")
@click.option(
    "--background", default="0,0,0", show_default=True, metavar="R,G,B", help="Linear RGB background."
)
@click.option(
    "--strip-format",
    type=click.Choice(["webp", "gif", "mp4", "none"]),
    default="webp",
    show_default=True,
    help="Animation for an orbit or a rotating environment.",
)
@click.option(
    "--fps", type=float, default=12.0, show_default=True, help="Frames per second of the animation."
)
@click.option(
    "--out", type=click.Path(file_okay=False, path_type=Path), required=True, help="Folder for the frames."
)
@click.option("--progress/--no-progress", default=True, show_default=True)
@DEVICE_OPTION
def relight_command(
    avatar,
    olat,
    point_lights,
    envmap,
    fitted_lighting,
    rotate,
    camera_source,
    data,
    subject,
    count,
    size,
    distance,
    image_scale,
    exposure,
    exr,
    background,
    strip_format,
    fps,
    out,
    progress,
    device,
) -> None:
    """Relight a fitted avatar: sRGB PNG frames, a contact sheet and, for an orbit or a rotating
    environment, an animated strip.

    \b
    Examples:
      relightanyone relight s02.avatar --olat 3 --out renders/
      relightanyone relight s02.avatar --point-light 0.5,0.3,0.8 --point-light -0.6,0,0.5,1,0.8,0.6 --out renders/
      relightanyone relight s02.avatar --envmap studio.exr --rotate 24 --cameras orbit --count 1 --out renders/
      relightanyone relight s02.avatar --fitted-lighting --cameras orbit --count 36 --size 384 --out renders/
    """
    import torch
    from PIL import Image

    from relightanyone.model.fit.avatar_tools import (
        contact_sheet,
        dataset_cameras,
        fitted_cameras,
        orbit_cameras_around,
        parse_floats,
        render_frames,
        safe_name,
        save_frames,
        write_strip,
    )

    stops = parse_exposure(exposure)
    try:
        background_rgb = torch.tensor(parse_floats(background, (3,), "--background"), dtype=torch.float32)
    except ValueError as error:
        raise click.BadParameter(str(error), param_hint="--background") from error
    if (data is None) != (subject is None):
        raise click.UsageError("--data and --subject go together (cameras of that subject in that dataset)")
    if data is not None and camera_source != "dataset":
        raise click.UsageError("--data/--subject choose dataset cameras; drop them or use --cameras dataset")
    if image_scale <= 0:
        raise click.BadParameter(f"must be positive, got {image_scale}", param_hint="--image-scale")
    check_one_lighting(olat, point_lights, envmap, fitted_lighting, rotate)
    fitted = load_avatar(avatar, device)
    lightings = chosen_lightings(fitted, olat, point_lights, envmap, fitted_lighting, rotate)
    try:
        if camera_source == "orbit":
            cameras = orbit_cameras_around(fitted, count, size, distance)
        else:
            if data is not None:
                if not Path(data).is_dir():
                    raise click.BadParameter(f"{data}: not a normalized dataset folder", param_hint="--data")
                cameras = dataset_cameras(data, subject=subject)
            else:
                cameras = fitted_cameras(fitted, avatar)
            if image_scale != 1.0:
                cameras = cameras.resize(image_scale)
    except (ValueError, FileNotFoundError) as error:
        raise click.ClickException(str(error)) from error

    out.mkdir(parents=True, exist_ok=True)
    saved = save_frames(render_frames(fitted, cameras, lightings, background_rgb, progress), out, stops, exr)
    encoded = saved.encoded
    frames = saved.frames
    columns = len(lightings) if len(lightings) > 1 else None
    labels = [f"{camera} {label}" for camera, label in frames]
    Image.fromarray(contact_sheet(encoded, labels, columns)).save(out / "contact_sheet.png")
    strips = []
    if strip_format != "none":
        names = list(dict.fromkeys(camera for camera, _ in frames))
        if len(lightings) > 1:  # a rotating environment: one animation per camera
            for camera in names:
                sequence = [e for e, (c, _) in zip(encoded, frames, strict=True) if c == camera]
                strips.append(
                    write_strip(out / f"strip_{safe_name(camera)}.{strip_format}", sequence, fps).name
                )
        elif camera_source == "orbit" and len(names) > 1:
            strips.append(write_strip(out / f"strip.{strip_format}", encoded, fps).name)
    report = {
        "avatar": str(avatar),
        "subject": fitted.metadata.get("subject"),
        "lightings": [named.label for named in lightings],
        "cameras": list(dict.fromkeys(camera for camera, _ in frames)),
        "exposure_stops": stops,
        "exposure_gain": saved.gain,
        "frames": saved.files,
        "contact_sheet": "contact_sheet.png",
        "strips": strips,
    }
    (out / "relight.json").write_text(json.dumps(report, indent=2) + "\n")
    click.echo(f"wrote {len(frames)} frames, contact_sheet.png{''.join(', ' + s for s in strips)} to {out}")


@click.command("export")
@click.argument("avatar", type=click.Path(path_type=Path))
@lighting_options
@click.option(
    "--view",
    default=None,
    metavar="X,Y,Z",
    help="Camera centre (canonical metres) the view-dependent colours are baked for; default: in front of the face.",
)
@click.option(
    "--colour-space",
    type=click.Choice(["srgb", "linear"]),
    default="srgb",
    show_default=True,
    help="srgb: display-referred colours for splat viewers; linear: scene-linear.",
)
@click.option(
    "--exposure",
    type=float,
    default=0.0,
    show_default=True,
    help="Exposure in stops applied to the linear colours before encoding.",
)
@click.option(
    "--sh-degree",
    type=click.IntRange(0, 3),
    default=3,
    show_default=True,
    help="SH degree the PLY declares (higher bands are zero).",
)
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The .ply file to write."
)
@DEVICE_OPTION
def export_command(
    avatar, olat, point_lights, envmap, fitted_lighting, view, colour_space, exposure, sh_degree, out, device
) -> None:
    """Export a fitted avatar relit under one lighting as a standard 3D Gaussian Splatting PLY.

    \b
    Example:
      relightanyone export s02.avatar --envmap studio.exr --out s02_studio.ply
    """
    import torch

    from relightanyone.model.fit.avatar_tools import export_gaussians, frontal_view, parse_floats
    from relightanyone.model.fit.ply import write_gaussian_ply

    check_one_lighting(olat, point_lights, envmap, fitted_lighting)
    fitted = load_avatar(avatar, device)
    (named,) = chosen_lightings(fitted, olat, point_lights, envmap, fitted_lighting)
    try:
        position = (
            frontal_view(fitted)
            if view is None
            else torch.tensor(parse_floats(view, (3,), "--view"), dtype=torch.float32)
        )
    except ValueError as error:
        raise click.BadParameter(str(error), param_hint="--view") from error
    gaussians = export_gaussians(fitted, named.lighting, position, colour_space, 2.0**exposure)
    write_gaussian_ply(out, sh_degree=sh_degree, **gaussians)
    click.echo(
        f"wrote {out}: {fitted.gaussian_count} Gaussians under {named.label}, {colour_space} colours, "
        f"view from {[round(float(v), 4) for v in position]}"
    )


COMMANDS: dict[str, click.Command] = {"relight": relight_command, "export": export_command}
