"""Model commands: ``align-colour``, ``train stage1|stage2``, ``render stage1``, ``fit``, ``relight`` and
``export``.

Only click declarations and thin bodies live here; the work is done by the library functions they call
(:mod:`relightanyone.model.train`, :mod:`relightanyone.model.fit`). torch and the model are imported
inside the command bodies, so that ``relightanyone --help`` stays instant; option values are parsed by
pure-Python functions (:mod:`relightanyone.model.fit.option_values`) before anything heavy loads.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from relightanyone.cli_options import (
    ANY_PATH,
    EXISTING_FOLDER,
    device_option,
    loader_workers_option,
    options,
    out_option,
    parsed_by,
    precision_option,
    preset_option,
    seed_option,
    threads_option,
)
from relightanyone.model.fit.option_values import parse_exposure, parse_point_lights, parse_triple

MODEL_PRESET_OPTION = preset_option("tiny", "Model size and schedule.")
ITERATIONS_OPTION = click.option(
    "--iterations", type=int, default=None, help="Override the preset's iterations."
)
WARMUP_ITERATIONS_OPTION = click.option(
    "--warmup-iterations", type=int, default=None, help="Override the preset's colour warm-up iterations."
)
BATCH_SIZE_OPTION = click.option(
    "--batch-size", type=int, default=None, help="Override the preset's batch size (per process)."
)
EVAL_VIEWS_OPTION = click.option(
    "--eval-views", type=int, default=None, help="Held-out views per dataset to score (default: all)."
)
RESUME_OPTION = click.option(
    "--resume/--no-resume",
    default=True,
    show_default=True,
    help="Continue from RUN/checkpoint.pt when present.",
)
RUN_OUT_HELP = "Run folder to write (or resume)."


def _datasets_option(help: str):
    """``--data DIR`` (repeatable, at least one): the normalized datasets to train on."""
    return click.option("--data", "data", multiple=True, required=True, type=EXISTING_FOLDER, help=help)


def _set_threads(threads: int | None) -> None:
    """Use ``threads`` CPU threads in torch (None: torch's choice)."""
    if threads is not None:
        import torch

        torch.set_num_threads(threads)


@click.command("align-colour")
@_datasets_option("Normalized dataset folder (repeat for each dataset stage 1 will train on).")
@click.option(
    "--uncalibrated",
    multiple=True,
    required=True,
    metavar="NAME",
    help="Dataset without colour calibration (repeatable): its 3x3 colour matrix is learned.",
)
@click.option(
    "--per-camera",
    multiple=True,
    metavar="NAME",
    help="Uncalibrated dataset whose cameras each get per-channel gains on its 3x3 after the warm-up "
    "(repeatable; default: every --uncalibrated dataset).",
)
@click.option(
    "--no-per-camera",
    is_flag=True,
    help="Learn only one 3x3 per uncalibrated dataset (the paper's alignment), no per-camera matrices.",
)
@MODEL_PRESET_OPTION
@WARMUP_ITERATIONS_OPTION
@seed_option()
@EVAL_VIEWS_OPTION
@threads_option()
@device_option()
@out_option("Folder for the warm-up run and one dataset view per --data.")
def align_colour_command(
    data,
    uncalibrated,
    per_camera,
    no_per_camera,
    preset,
    warmup_iterations,
    seed,
    eval_views,
    threads,
    device,
    out,
) -> None:
    """Learn the colour matrices of uncalibrated datasets (warm-up without lighting codes, paper 4.1).

    After the warm-up, every camera of an uncalibrated rig gets the dataset's 3x3 with per-channel gains of
    its own, from its training views (a rig's cameras differ in colour response); a camera seen too little
    keeps its dataset's.

    Writes OUT/warmup/ (the warm-up run), OUT/<dataset>/ for every --data: a view of the dataset (links to
    its files; the source is not modified) carrying colour_alignment.json for the uncalibrated ones, and
    OUT/colour_alignment.json (matrices and held-out PSNR/SSIM without and with them). Train stage 1 on the
    views: relightanyone train stage1 --data OUT/<dataset> ... --no-colour-warmup

    Example: relightanyone align-colour --data out/d1 --data out/ava256 --uncalibrated ava256 --out aligned
    """
    from relightanyone.model.networks.presets import get_preset, with_overrides
    from relightanyone.model.train.colour_warmup import align_colours

    _set_threads(threads)
    chosen = with_overrides(get_preset(preset), warmup_iterations=warmup_iterations)
    if no_per_camera and per_camera:
        raise click.UsageError("--per-camera and --no-per-camera exclude each other")
    chosen_per_camera = () if no_per_camera else (tuple(per_camera) or None)
    report = align_colours(
        list(data), tuple(uncalibrated), chosen, out, seed, eval_views, device, chosen_per_camera
    )
    click.echo("colour matrices (render -> dataset): " + json.dumps(report.get("colour_matrices", {})))
    for name, cameras in sorted(report.get("camera_matrices", {}).items()):
        click.echo(f"{name}: {len(cameras)} camera(s) with their own matrix")
    click.echo(f"dataset views for stage 1: {', '.join(str(out / n) for n in report['datasets'])}")


@click.group("train")
def train_group() -> None:
    """Train the Gaussian head model (stage 1: full-on multi-identity model)."""


@train_group.command("stage1")
@_datasets_option("Normalized dataset folder (repeat for each dataset).")
@MODEL_PRESET_OPTION
@out_option(RUN_OUT_HELP)
@click.option(
    "--uncalibrated",
    multiple=True,
    metavar="NAME",
    help="Dataset without colour calibration (repeatable): a warm-up learns its 3x3 colour matrix first.",
)
@click.option(
    "--colour-warmup/--no-colour-warmup",
    default=True,
    show_default=True,
    help="Run the colour warm-up for --uncalibrated datasets (off: reuse matrices already stored).",
)
@click.option(
    "--lighting-code/--no-lighting-code",
    default=True,
    show_default=True,
    help="Learn a lighting code per dataset (off: the ablation without z_l; datasets are aligned only by "
    "their colour matrices).",
)
@ITERATIONS_OPTION
@WARMUP_ITERATIONS_OPTION
@BATCH_SIZE_OPTION
@seed_option()
@RESUME_OPTION
@EVAL_VIEWS_OPTION
@threads_option()
@device_option()
@precision_option()
@loader_workers_option()
def train_stage1_command(
    data,
    preset,
    out,
    uncalibrated,
    colour_warmup,
    lighting_code,
    iterations,
    warmup_iterations,
    batch_size,
    seed,
    resume,
    eval_views,
    threads,
    device,
    precision,
    loader_workers,
) -> None:
    """Train stage 1 on one or more normalized datasets.

    Example: relightanyone train stage1 --data out/d1 --data out/ava256 --uncalibrated ava256 --preset demo --out runs/s1

    Under torchrun (torchrun --nproc_per_node 2 -m relightanyone train stage1 ...) the processes train
    data-parallel. Run folder: checkpoint.pt, run.json, metrics.json, tensorboard/ (and warmup/).
    """
    from relightanyone.model.networks.presets import get_preset, with_overrides
    from relightanyone.model.train.colour_warmup import run_colour_warmup
    from relightanyone.model.train.stage1 import Stage1Config, train_stage1

    _set_threads(threads)
    chosen = with_overrides(
        get_preset(preset), iterations=iterations, warmup_iterations=warmup_iterations, batch_size=batch_size
    )
    if uncalibrated and colour_warmup:
        warm = run_colour_warmup(
            list(data),
            out,
            chosen,
            tuple(uncalibrated),
            seed,
            eval_views_per_dataset=eval_views,
            device=device,
        )
        if warm:
            click.echo("colour warm-up matrices (render -> dataset): " + json.dumps(warm["colour_matrices"]))
    config = Stage1Config(
        data=list(data),
        out=out,
        preset=chosen,
        seed=seed,
        lighting_code=lighting_code,
        resume=resume,
        eval_views_per_dataset=eval_views,
        device=device,
        precision=precision,
        loader_workers=loader_workers,
    )
    metrics = train_stage1(config)
    for name, values in (metrics.get("held_out") or {}).items():
        click.echo(
            f"{name}: held-out PSNR {values['psnr']:.2f} dB, SSIM {values['ssim']:.4f} ({values['views']} views)"
        )


@train_group.command("stage2")
@click.option(
    "--data",
    type=EXISTING_FOLDER,
    required=True,
    help="The normalized OLAT dataset (full-on and olat-KKK frames, lights.arrow).",
)
@click.option(
    "--stage1",
    "stage1_run",
    type=EXISTING_FOLDER,
    default=None,
    help="The stage-1 run to freeze (trained with this dataset); not used with --single-stage.",
)
@out_option(RUN_OUT_HELP)
@MODEL_PRESET_OPTION
@click.option(
    "--single-stage",
    is_flag=True,
    help="Train the single-stage baseline instead: stage 1 with relightable decoders, OLAT dataset only.",
)
@click.option(
    "--single-stage-loss",
    type=click.Choice(["background", "masked"]),
    default="background",
    show_default=True,
    help="The baseline's image loss: over a random background on the whole crop, or inside the mask only.",
)
@click.option(
    "--match-budget",
    nargs=2,
    type=EXISTING_FOLDER,
    default=None,
    metavar="STAGE1_RUN STAGE2_RUN",
    help="Train as many views as these two runs together (iterations = their views / batch size); "
    "gives the single-stage baseline the two-stage model's budget. Replaces --iterations.",
)
@click.option(
    "--match-share",
    type=click.FloatRange(min=0.0, min_open=True, max=1.0),
    default=1.0,
    show_default=True,
    help="With --match-budget: train this share of those runs' views (1: the same budget; a smoke run "
    "may train less, and the evaluation shows every model's budget beside its numbers).",
)
@ITERATIONS_OPTION
@BATCH_SIZE_OPTION
@seed_option()
@RESUME_OPTION
@threads_option()
@device_option()
@precision_option()
@click.option(
    "--checkpoint-maps/--no-checkpoint-maps",
    default=False,
    show_default=True,
    help="Recompute the trained networks' UV-map activations in the backward pass (less memory, ~1 more "
    "forward pass of those networks per step; the same gradients).",
)
@loader_workers_option()
@click.option(
    "--accumulation",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Split each batch into this many micro-batches and accumulate their gradients (less memory, the "
    "same update; see `relightanyone plan`).",
)
def train_stage2_command(
    data,
    stage1_run,
    out,
    preset,
    single_stage,
    single_stage_loss,
    match_budget,
    match_share,
    iterations,
    batch_size,
    seed,
    resume,
    threads,
    device,
    precision,
    checkpoint_maps,
    loader_workers,
    accumulation,
) -> None:
    """Train stage 2 (relighting UNet on a frozen stage-1 run) or the single-stage baseline.

    Example: relightanyone train stage2 --data out/d1 --stage1 runs/s1 --preset demo --out runs/s2

    Under torchrun (torchrun --nproc_per_node 2 -m relightanyone train stage2 ...) the processes train
    data-parallel; --batch-size is per process.
    """
    if not single_stage and stage1_run is None:
        raise click.UsageError(
            "stage 2 needs --stage1 RUN (a stage-1 run trained with this dataset), or --single-stage"
        )
    from relightanyone.model.networks.presets import get_preset, get_stage2_preset, with_overrides
    from relightanyone.model.train.budget import matched_iterations, two_stage_budget
    from relightanyone.model.train.stage2 import Stage2Config, train_stage2

    _set_threads(threads)
    chosen = with_overrides(get_stage2_preset(preset), iterations=iterations, batch_size=batch_size)
    if match_share != 1.0 and match_budget is None:
        raise click.UsageError("--match-share needs --match-budget STAGE1_RUN STAGE2_RUN")
    if match_budget is not None:
        if iterations is not None:
            raise click.UsageError("give --iterations or --match-budget, not both")
        budget = two_stage_budget(*match_budget)
        views = math.ceil(budget["samples"] * match_share)
        chosen = chosen.replace(iterations=matched_iterations(views, chosen.batch_size))
        share = "" if match_share == 1.0 else f" × {match_share:g} = {views} views"
        click.echo(
            f"matching the budget of {match_budget[0]} + {match_budget[1]}: {budget['samples']} views"
            f"{share} = {chosen.iterations} iterations of {chosen.batch_size}"
        )
    config = Stage2Config(
        data=data,
        out=out,
        preset=chosen,
        stage1_run=None if single_stage else stage1_run,
        single_stage=single_stage,
        stage1_preset=get_preset(preset) if single_stage else None,
        single_stage_loss=single_stage_loss,
        seed=seed,
        resume=resume,
        device=device,
        precision=precision,
        checkpoint_maps=checkpoint_maps,
        loader_workers=loader_workers,
        accumulation=accumulation,
    )
    metrics = train_stage2(config)
    last = metrics.get("last_losses") or {}
    click.echo(
        f"{metrics['mode']}: {metrics['iterations']} iterations, last loss {last.get('total', float('nan')):.4g} "
        f"(L1 {last.get('l1', float('nan')):.4g}); wrote {out}"
    )


@click.group("render")
def render_group() -> None:
    """Render trained models."""


@render_group.command("stage1")
@click.argument("run", type=EXISTING_FOLDER)
@click.option(
    "--subject", default=None, help="Subject as <dataset>/<subject> (or a name unique across datasets)."
)
@click.option(
    "--lighting-code", default=None, metavar="DATASET", help="Render under this dataset's lighting code."
)
@click.option("--cameras", type=click.Choice(["dataset", "orbit"]), default="dataset", show_default=True)
@click.option("--orbit-count", type=int, default=8, show_default=True, help="Cameras on the orbit.")
@click.option(
    "--lighting-grid",
    is_flag=True,
    help="Write lighting_grid.png: a subject of every dataset under every dataset's lighting code.",
)
@out_option("Folder for the PNGs.")
@device_option()
def render_stage1_command(
    run, subject, lighting_code, cameras, orbit_count, lighting_grid, out, device
) -> None:
    """Render a stage-1 subject to PNGs (sRGB); report colour shift and geometry when swapping lighting codes."""
    if subject is None and not lighting_grid:
        raise click.UsageError("give --subject, --lighting-grid, or both")
    from relightanyone.model.device import resolve_device
    from relightanyone.model.train.run import render_run

    reports = render_run(
        run, out, subject, lighting_code, cameras, orbit_count, lighting_grid, resolve_device(device)
    )
    shifted = reports.get("subject", {})
    if "mean_colour_shift" in shifted:
        click.echo(
            f"lighting code {shifted['lighting_code']} instead of {shifted['own_lighting_code']}: "
            f"mean colour shift {[round(v, 4) for v in shifted['mean_colour_shift']]} "
            f"({100 * shifted['relative_colour_shift']:.1f} %), geometry identical: "
            f"{shifted['geometry_identical']}"
        )
    click.echo(f"wrote {out}")


@click.command("fit")
@click.option("--stage1", "stage1_run", type=EXISTING_FOLDER, required=True)
@click.option(
    "--stage2", "stage2_run", type=EXISTING_FOLDER, required=True, help="The stage-2 run trained on --stage1."
)
@click.option(
    "--data",
    type=EXISTING_FOLDER,
    required=True,
    help="Normalized dataset holding the subject's images, cameras and tracked meshes.",
)
@click.option("--subject", "subjects", multiple=True, help="Subject to fit (repeatable; default: --split).")
@click.option(
    "--split",
    default="test",
    show_default=True,
    help="Without --subject: fit every subject of this split (the held-out subjects by default).",
)
@click.option(
    "--frame", type=int, default=None, help="Frame to fit (default: the subject's first full-on frame)."
)
@click.option("--pattern", default="full", show_default=True, help="Lighting pattern of the input images.")
@click.option(
    "--camera",
    "cameras",
    multiple=True,
    help="Input camera (repeatable; default: all cameras of the frame). One camera = a single-image fit.",
)
@click.option(
    "--input-lighting",
    type=click.Choice(["rig", "dataset"]),
    default="rig",
    show_default=True,
    help="rig: the images are lit by an unknown lighting of the OLAT rig, estimated with the fit. dataset: "
    "--data is one of stage 1's own datasets (a held-out subject of a flat-lit capture, say) and the images "
    "are rendered under its lighting code, so the subject's level comes from what stage 1 learned of it.",
)
@click.option("--inversion-iterations", type=int, default=300, show_default=True)
@click.option("--finetune-iterations", type=int, default=300, show_default=True)
@click.option("--views-per-step", type=int, default=4, show_default=True)
@click.option("--image-scale", type=float, default=1.0, show_default=True, help="Resize inputs (and K).")
@seed_option()
@threads_option()
@device_option()
@out_option("Folder for <subject>.avatar files and fit_report.json.")
def fit_command(
    stage1_run,
    stage2_run,
    data,
    subjects,
    split,
    frame,
    pattern,
    cameras,
    inversion_iterations,
    finetune_iterations,
    views_per_step,
    image_scale,
    input_lighting,
    seed,
    threads,
    device,
    out,
) -> None:
    """Fit unseen subjects (inversion, then finetuning with the locality regulariser, paper 3.3).

    Each subject becomes OUT/<subject>.avatar: a relightable avatar for `relightanyone relight` and
    `relightanyone export`. An avatar already in OUT is kept (delete it to fit again).

    Example: relightanyone fit --stage1 runs/s1 --stage2 runs/s2 --data out/faceolat --split test --out avatars
    """
    from relightanyone.model.device import resolve_device
    from relightanyone.model.fit.fitter import FitSettings
    from relightanyone.model.fit.subjects import fit_subjects, subjects_to_fit, write_fit_report

    _set_threads(threads)
    settings = FitSettings(
        inversion_iterations=inversion_iterations,
        finetune_iterations=finetune_iterations,
        views_per_step=views_per_step,
        seed=seed,
    )
    fits = []
    for fit in fit_subjects(
        stage1_run,
        stage2_run,
        data,
        subjects_to_fit(data, subjects, split, pattern),
        out,
        frame=frame,
        cameras=list(cameras) or None,
        pattern=pattern,
        settings=settings,
        image_scale=image_scale,
        device=resolve_device(device),
        input_lighting=input_lighting,
    ):
        fits.append(fit)
        if fit.kept:
            click.echo(f"{fit.subject}: {fit.avatar} exists, kept")
        else:
            click.echo(
                f"{fit.subject}: {fit.views} views, L1 {fit.losses.get('l1', float('nan')):.4g}; wrote {fit.avatar}"
            )
    write_fit_report(out, fits)


LIGHTING_OPTIONS = options(
    click.option("--olat", type=int, default=None, metavar="K", help="Light K of the avatar's OLAT rig."),
    click.option(
        "--point-light",
        "point_lights",
        multiple=True,
        metavar="X,Y,Z[,R,G,B]",
        callback=parsed_by(parse_point_lights),
        help="A point light in canonical metres (repeatable); R,G,B linear intensity, default the rig's mean light.",
    ),
    click.option(
        "--envmap",
        type=ANY_PATH,
        default=None,
        help="Equirectangular environment map (.exr or .hdr, linear, +y up).",
    ),
    click.option(
        "--fitted-lighting",
        is_flag=True,
        help="The lighting estimated from the images the avatar was fitted to.",
    ),
)


@click.command("relight")
@click.argument("avatar", type=ANY_PATH)
@LIGHTING_OPTIONS
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
    type=ANY_PATH,
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
    callback=parsed_by(parse_exposure),
    help="Exposure of the PNGs in stops (linear × 2^stops), or 'auto'.",
)
@click.option("--exr", is_flag=True, help="Also write every frame as a linear float32 EXR.")
@click.option(
    "--background",
    default="0,0,0",
    show_default=True,
    metavar="R,G,B",
    callback=parsed_by(parse_triple),
    help="Linear RGB background.",
)
@click.option(
    "--strip-format",
    type=click.Choice(["webp", "gif", "mp4", "none"]),
    default="webp",
    show_default=True,
    help="Animation for an orbit or a rotating environment.",
)
@click.option(
    "--fps",
    type=click.FloatRange(min=0, min_open=True),
    default=12.0,
    show_default=True,
    help="Frames per second of the animation.",
)
@out_option("Folder for the frames.")
@click.option("--progress/--no-progress", default=True, show_default=True)
@device_option()
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
    from relightanyone.model.fit.lighting_choice import LightingChoice, chosen_lightings
    from relightanyone.model.fit.relight import CameraChoice, chosen_cameras, relight_into

    lighting = LightingChoice(olat, point_lights, envmap, fitted_lighting, rotate)
    camera_choice = CameraChoice(camera_source, data, subject, count, size, distance, image_scale)
    lighting.check()
    camera_choice.check()
    fitted, source = _load_avatar(avatar, device)
    lightings = chosen_lightings(fitted, lighting)
    cameras = chosen_cameras(fitted, source, camera_choice)
    report = relight_into(
        fitted,
        avatar,
        cameras,
        lightings,
        out,
        stops=exposure,
        exr=exr,
        background=background,
        strip_format=strip_format,
        fps=fps,
        orbit=camera_source == "orbit",
        progress=progress,
    )
    frames = len(report["cameras"]) * len(report["lightings"])
    click.echo(
        f"wrote {frames} frames, contact_sheet.png{''.join(', ' + s for s in report['strips'])} to {out}"
    )


@click.command("export")
@click.argument("avatar", type=ANY_PATH)
@LIGHTING_OPTIONS
@click.option(
    "--view",
    default=None,
    metavar="X,Y,Z",
    callback=parsed_by(parse_triple),
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
@out_option("The .ply file to write.", file=True)
@device_option()
def export_command(
    avatar, olat, point_lights, envmap, fitted_lighting, view, colour_space, exposure, sh_degree, out, device
) -> None:
    """Export a fitted avatar relit under one lighting as a standard 3D Gaussian Splatting PLY.

    \b
    Example:
      relightanyone export s02.avatar --envmap studio.exr --out s02_studio.ply
    """
    from relightanyone.model.fit.lighting_choice import LightingChoice, chosen_lightings
    from relightanyone.model.fit.relight import export_ply

    lighting = LightingChoice(olat, point_lights, envmap, fitted_lighting)
    lighting.check()
    fitted, _ = _load_avatar(avatar, device)
    (named,) = chosen_lightings(fitted, lighting)
    position = export_ply(fitted, named, out, view, colour_space, exposure, sh_degree)
    click.echo(
        f"wrote {out}: {fitted.gaussian_count} Gaussians under {named.label}, {colour_space} colours, "
        f"view from {[round(float(v), 4) for v in position]}"
    )


def _load_avatar(path: Path, device: str):
    """The avatar at ``path`` on ``device`` and its file (:func:`~relightanyone.model.fit.relight.load_avatar`);
    says which file was used when ``path`` is a folder of avatars."""
    from relightanyone.model.fit.relight import load_avatar

    avatar, source = load_avatar(path, device)
    if source != Path(path):
        click.echo(f"using {source} (the first avatar in {path})", err=True)
    return avatar, source


@click.command("plan")
@preset_option("paper", "Preset of stage 1 and stage 2 (sizes and batch).")
@click.option(
    "--batch-size", type=click.IntRange(min=1), default=None, help="Override the presets' batch size."
)
@click.option("--crop", type=click.IntRange(min=8), default=None, help="Override the presets' crop size.")
@click.option(
    "--lights",
    type=click.IntRange(min=1),
    default=None,
    help="Lights of the OLAT rig (default: those of --data when given, else 150).",
)
@click.option(
    "--data",
    type=EXISTING_FOLDER,
    default=None,
    help="A normalized dataset: its template mesh sets the Gaussians, its rig the lights.",
)
@click.option("--json", "json_path", type=ANY_PATH, default=None, help="Also write the plan as JSON here.")
def plan_command(preset, batch_size, crop, lights, data, json_path) -> None:
    """Estimate peak memory per GPU of stage 1, stage 2, the single-stage baseline and fitting, and
    propose batch, accumulation, precision and checkpointing that fit 24, 48 and 80 GB GPUs.

    Nothing is allocated: the networks are traced on torch's meta device.

    Example: relightanyone plan --preset paper --data out/faceolat
    """
    from relightanyone.model.train.plan import DEFAULT_RIG_LIGHTS, PlanRequest, format_plan, memory_plan

    template = None
    if data is not None:
        from relightanyone.format.reader import NormalizedDataset
        from relightanyone.format.schema import TEMPLATE_NAME

        template = data / TEMPLATE_NAME if (data / TEMPLATE_NAME).is_file() else None
        lights = lights or len(NormalizedDataset(data).lights()) or None
    request = PlanRequest(preset, batch_size, crop, lights or DEFAULT_RIG_LIGHTS, template=template)
    plan = memory_plan(request)
    click.echo(format_plan(plan))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(plan, indent=2) + "\n")


COMMANDS: dict[str, click.Command] = {
    "align-colour": align_colour_command,
    "train": train_group,
    "render": render_group,
    "fit": fit_command,
    "relight": relight_command,
    "export": export_command,
    "plan": plan_command,
}
