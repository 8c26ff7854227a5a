"""Model commands: ``train stage1`` and ``render stage1``.

Heavy imports (torch, the model) happen inside the commands so ``relightanyone --help`` stays fast.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from relightanyone.model.avatar_cli import COMMANDS as AVATAR_COMMANDS

PRESET_NAMES = ("tiny", "demo", "small", "paper")


@click.group("train")
def train_group() -> None:
    """Train the Gaussian head model (stage 1: full-on multi-identity model)."""


@train_group.command("stage1")
@click.option(
    "--data",
    "data",
    multiple=True,
    required=True,
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Normalized dataset folder (repeat for each dataset).",
)
@click.option(
    "--preset",
    type=click.Choice(PRESET_NAMES),
    default="tiny",
    show_default=True,
    help="Model size and schedule.",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Run folder to write (or resume).",
)
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
@click.option("--iterations", type=int, default=None, help="Override the preset's iteration count.")
@click.option(
    "--warmup-iterations", type=int, default=None, help="Override the preset's warm-up iteration count."
)
@click.option("--batch-size", type=int, default=None, help="Override the preset's batch size (per process).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--resume/--no-resume",
    default=True,
    show_default=True,
    help="Continue from RUN/checkpoint.pt when present.",
)
@click.option(
    "--eval-views", type=int, default=None, help="Held-out views per dataset to evaluate (default: all)."
)
@click.option(
    "--threads",
    type=int,
    default=None,
    help="CPU threads for torch (default: torch's choice; use 1 on a machine shared with other jobs).",
)
def train_stage1_command(
    data,
    preset,
    out,
    uncalibrated,
    colour_warmup,
    iterations,
    warmup_iterations,
    batch_size,
    seed,
    resume,
    eval_views,
    threads,
) -> None:
    """Train stage 1 on one or more normalized datasets.

    Example: relightanyone train stage1 --data out/d1 --data out/ava256 --uncalibrated ava256 --preset demo --out runs/s1

    Under torchrun (torchrun --nproc_per_node 2 -m relightanyone train stage1 ...) the processes train
    data-parallel. Run folder: checkpoint.pt, run.json, metrics.json, tensorboard/ (and warmup/).
    """
    import torch

    from relightanyone.model.networks.presets import get_preset
    from relightanyone.model.train.colour_warmup import run_colour_warmup
    from relightanyone.model.train.stage1 import Stage1Config, train_stage1

    if threads is not None:
        torch.set_num_threads(threads)
    chosen = get_preset(preset)
    changes = {
        k: v
        for k, v in (
            ("iterations", iterations),
            ("warmup_iterations", warmup_iterations),
            ("batch_size", batch_size),
        )
        if v is not None
    }
    chosen = chosen.replace(**changes) if changes else chosen
    try:
        if uncalibrated and colour_warmup:
            warm = run_colour_warmup(
                list(data), out, chosen, tuple(uncalibrated), seed, eval_views_per_dataset=eval_views
            )
            if warm:
                click.echo(
                    "colour warm-up matrices (render -> dataset): " + json.dumps(warm["colour_matrices"])
                )
        metrics = train_stage1(
            Stage1Config(
                data=list(data),
                out=out,
                preset=chosen,
                seed=seed,
                resume=resume,
                eval_views_per_dataset=eval_views,
            )
        )
    except (ValueError, FileNotFoundError) as error:
        raise click.ClickException(str(error)) from error
    if metrics.get("held_out"):
        for name, values in metrics["held_out"].items():
            click.echo(
                f"{name}: held-out PSNR {values['psnr']:.2f} dB, SSIM {values['ssim']:.4f} ({values['views']} views)"
            )


@click.command("align-colour")
@click.option(
    "--data",
    "data",
    multiple=True,
    required=True,
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Normalized dataset folder (repeat for each dataset stage 1 will train on).",
)
@click.option(
    "--uncalibrated",
    multiple=True,
    required=True,
    metavar="NAME",
    help="Dataset without colour calibration (repeatable): its 3x3 colour matrix is learned.",
)
@click.option("--preset", type=click.Choice(PRESET_NAMES), default="tiny", show_default=True)
@click.option("--warmup-iterations", type=int, default=None, help="Override the preset's warm-up length.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--eval-views", type=int, default=None, help="Held-out views per dataset to score (default: all)."
)
@click.option("--threads", type=int, default=None, help="CPU threads for torch (default: torch's choice).")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder for the warm-up run and one dataset view per --data.",
)
def align_colour_command(
    data, uncalibrated, preset, warmup_iterations, seed, eval_views, threads, out
) -> None:
    """Learn the colour matrix of uncalibrated datasets (warm-up without lighting codes, paper 4.1).

    Writes OUT/warmup/ (the warm-up run), OUT/<dataset>/ for every --data: a view of the dataset (links to
    its files; the source is not modified) carrying colour_alignment.json for the uncalibrated ones, and
    OUT/colour_alignment.json (matrices and held-out PSNR/SSIM without and with them). Train stage 1 on the
    views: relightanyone train stage1 --data OUT/<dataset> ... --no-colour-warmup

    Example: relightanyone align-colour --data out/d1 --data out/ava256 --uncalibrated ava256 --out aligned
    """
    import torch

    from relightanyone.format.dataset_view import link_dataset_view
    from relightanyone.format.reader import load_manifest
    from relightanyone.model.networks.presets import get_preset
    from relightanyone.model.train.colour_warmup import run_colour_warmup

    if threads is not None:
        torch.set_num_threads(threads)
    chosen = get_preset(preset)
    if warmup_iterations is not None:
        chosen = chosen.replace(warmup_iterations=warmup_iterations)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        names = {load_manifest(Path(d)).info.name: Path(d) for d in data}
        unknown = sorted(set(uncalibrated) - set(names))
        if unknown:
            raise ValueError(f"--uncalibrated {unknown} is not among the --data datasets {sorted(names)}")
        metrics = run_colour_warmup(
            list(data),
            out,
            chosen,
            tuple(uncalibrated),
            seed,
            eval_views_per_dataset=eval_views,
            views_dir=out,
        )
        for name, folder in names.items():
            if name not in uncalibrated:
                link_dataset_view(folder, out / name)
    except (ValueError, FileNotFoundError) as error:
        raise click.ClickException(str(error)) from error
    report = {
        "uncalibrated": sorted(uncalibrated),
        "datasets": {name: str(folder) for name, folder in names.items()},
        **{k: v for k, v in metrics.items() if k != "losses"},
    }
    (out / "colour_alignment.json").write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    click.echo("colour matrices (render -> dataset): " + json.dumps(metrics.get("colour_matrices", {})))
    click.echo(f"dataset views for stage 1: {', '.join(str(out / n) for n in names)}")


@click.group("render")
def render_group() -> None:
    """Render trained models."""


@render_group.command("stage1")
@click.argument("run", type=click.Path(exists=True, file_okay=False, path_type=Path))
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
@click.option(
    "--out", type=click.Path(file_okay=False, path_type=Path), required=True, help="Folder for the PNGs."
)
def render_stage1_command(run, subject, lighting_code, cameras, orbit_count, lighting_grid, out) -> None:
    """Render a stage-1 subject to PNGs (sRGB); report colour shift and geometry when swapping lighting codes."""
    from relightanyone.model.train.run import lighting_alignment_grid, load_run, render_subject

    if subject is None and not lighting_grid:
        raise click.UsageError("give --subject, --lighting-grid, or both")
    try:
        loaded = load_run(run)
        reports = {}
        if subject is not None:
            reports["subject"] = render_subject(loaded, subject, out, lighting_code, cameras, orbit_count)
        if lighting_grid:
            reports["lighting_grid"] = lighting_alignment_grid(loaded, Path(out) / "lighting_grid.png")
    except (ValueError, FileNotFoundError) as error:
        raise click.ClickException(str(error)) from error
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "render_report.json").write_text(json.dumps(reports, indent=2) + "\n")
    subject_report = reports.get("subject", {})
    if "mean_colour_shift" in subject_report:
        click.echo(
            f"lighting code {subject_report['lighting_code']} instead of {subject_report['own_lighting_code']}: "
            f"mean colour shift {[round(v, 4) for v in subject_report['mean_colour_shift']]} "
            f"({100 * subject_report['relative_colour_shift']:.1f} %), geometry identical: "
            f"{subject_report['geometry_identical']}"
        )
    click.echo(f"wrote {out}")


COMMANDS: dict[str, click.Command] = {
    "train": train_group,
    "render": render_group,
    "align-colour": align_colour_command,
}


@train_group.command("stage2")
@click.option(
    "--data",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    required=True,
    help="The normalized OLAT dataset (full-on and olat-KKK frames, lights.arrow).",
)
@click.option(
    "--stage1",
    "stage1_run",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    default=None,
    help="The stage-1 run to freeze (trained with this dataset); not used with --single-stage.",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Run folder to write (or resume).",
)
@click.option(
    "--preset",
    type=click.Choice(PRESET_NAMES),
    default="tiny",
    show_default=True,
    help="Model size and schedule.",
)
@click.option(
    "--single-stage",
    is_flag=True,
    help="Train the single-stage baseline instead: stage 1 with relightable decoders, OLAT dataset only.",
)
@click.option("--iterations", type=int, default=None, help="Override the preset's iteration count.")
@click.option("--batch-size", type=int, default=None, help="Override the preset's batch size.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--resume/--no-resume",
    default=True,
    show_default=True,
    help="Continue from RUN/checkpoint.pt when present.",
)
def train_stage2_command(
    data, stage1_run, out, preset, single_stage, iterations, batch_size, seed, resume
) -> None:
    """Train stage 2 (relighting UNet on a frozen stage-1 run) or the single-stage baseline.

    Example: relightanyone train stage2 --data out/d1 --stage1 runs/s1 --preset demo --out runs/s2
    """
    from relightanyone.format.reader import IncompleteDatasetError
    from relightanyone.model.networks.presets import get_preset, get_stage2_preset
    from relightanyone.model.train.stage2 import Stage2Config, train_stage2

    chosen = get_stage2_preset(preset)
    changes = {k: v for k, v in (("iterations", iterations), ("batch_size", batch_size)) if v is not None}
    chosen = chosen.replace(**changes) if changes else chosen
    if not single_stage and stage1_run is None:
        raise click.UsageError(
            "stage 2 needs --stage1 RUN (a stage-1 run trained with this dataset), or --single-stage"
        )
    config = Stage2Config(
        data=data,
        out=out,
        preset=chosen,
        stage1_run=None if single_stage else stage1_run,
        single_stage=single_stage,
        stage1_preset=get_preset(preset) if single_stage else None,
        seed=seed,
        resume=resume,
    )
    try:
        metrics = train_stage2(config)
    except (ValueError, FileNotFoundError, IncompleteDatasetError) as error:
        raise click.ClickException(str(error)) from error
    last = metrics.get("last_losses") or {}
    click.echo(
        f"{metrics['mode']}: {metrics['iterations']} iterations, last loss {last.get('total', float('nan')):.4g} "
        f"(L1 {last.get('l1', float('nan')):.4g}); wrote {out}"
    )


@click.command("fit")
@click.option(
    "--stage1", "stage1_run", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True
)
@click.option(
    "--stage2",
    "stage2_run",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    required=True,
    help="The stage-2 run trained on --stage1.",
)
@click.option(
    "--data",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
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
@click.option("--inversion-iterations", type=int, default=300, show_default=True)
@click.option("--finetune-iterations", type=int, default=300, show_default=True)
@click.option("--views-per-step", type=int, default=4, show_default=True)
@click.option("--image-scale", type=float, default=1.0, show_default=True, help="Resize inputs (and K).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--threads", type=int, default=None, help="CPU threads for torch (default: torch's choice).")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder for <subject>.avatar files and fit_report.json.",
)
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
    seed,
    threads,
    out,
) -> None:
    """Fit unseen subjects (inversion, then finetuning with the locality regulariser, paper 3.3).

    Each subject becomes OUT/<subject>.avatar: a relightable avatar for `relightanyone relight` and
    `relightanyone export`. An avatar already in OUT is kept (delete it to fit again).

    Example: relightanyone fit --stage1 runs/s1 --stage2 runs/s2 --data out/faceolat --split test --out avatars
    """
    import torch

    from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
    from relightanyone.model.fit.fitter import FitSettings, fit_subject

    if threads is not None:
        torch.set_num_threads(threads)
    try:
        dataset = NormalizedDataset(data)
        chosen = list(subjects) or sorted(
            {k.split("/")[1] for k in dataset.select(splits=split, patterns=pattern)}
        )
    except (ValueError, FileNotFoundError, IncompleteDatasetError) as error:
        raise click.ClickException(str(error)) from error
    if not chosen:
        raise click.ClickException(
            f"{data}: no subject of split {split!r} has {pattern!r} rows; name subjects with --subject"
        )
    settings = FitSettings(
        inversion_iterations=inversion_iterations,
        finetune_iterations=finetune_iterations,
        views_per_step=views_per_step,
        seed=seed,
    )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = {}
    for subject in chosen:
        target = out / f"{subject}.avatar"
        if target.is_file():
            click.echo(f"{subject}: {target} exists, kept")
            continue
        try:
            avatar = fit_subject(
                stage1_run,
                stage2_run,
                data,
                subject,
                frame=frame,
                cameras=list(cameras) or None,
                pattern=pattern,
                settings=settings,
                image_scale=image_scale,
                out=target,
            )
        except (ValueError, FileNotFoundError, IncompleteDatasetError) as error:
            raise click.ClickException(f"{subject}: {error}") from error
        losses = avatar.metadata.get("final_losses", {})
        report[subject] = {"avatar": target.name, "views": len(avatar.metadata.get("cameras", [])), **losses}
        click.echo(
            f"{subject}: {len(avatar.metadata.get('cameras', []))} views, L1 {losses.get('l1', float('nan')):.4g}; wrote {target}"
        )
    previous = out / "fit_report.json"
    if previous.is_file():
        report = json.loads(previous.read_text()) | report
    previous.write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")


COMMANDS["fit"] = fit_command
COMMANDS.update(AVATAR_COMMANDS)
