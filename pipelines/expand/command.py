"""``relightanyone expand SOURCE_DATASET --stage1 RUN --stage2 RUN --out PARENT``: the OLAT expansion job.

The job (torch, the model) is imported inside the command so that ``relightanyone --help`` stays instant.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from relightanyone.cli_options import (
    EXISTING_FILE,
    EXISTING_FOLDER,
    device_option,
    dry_run_option,
    executor_option,
    fit_iterations_option,
    names_option,
    out_option,
    seed_option,
    workers_option,
)


@click.command("expand")
@click.argument("source", type=EXISTING_FOLDER)
@click.option(
    "--stage1",
    type=EXISTING_FOLDER,
    required=True,
    help="Stage-1 run folder (the one the stage-2 run was trained on).",
)
@click.option(
    "--stage2",
    type=EXISTING_FOLDER,
    required=True,
    help="Stage-2 run folder; its OLAT dataset's rig becomes the output's lights.arrow.",
)
@out_option(
    "Parent folder; the dataset is written to OUT/NAME and fitted avatars to OUT/NAME-avatars.", dest="parent"
)
@click.option("--name", default=None, help="Output dataset name (default: <source>-olat).")
@names_option("--subjects", "Only these subjects (repeatable or comma list).")
@names_option("--splits", "Only source rows of these splits (default: all).", metavar="train,test")
@click.option(
    "--envmap",
    "envmaps",
    multiple=True,
    type=EXISTING_FILE,
    help="Also render under this lat-long .exr/.hdr environment map, as pattern env-<file stem> (repeatable).",
)
@fit_iterations_option(
    (300, 300), "Inversion and finetuning steps for subjects the stage-1 run was not trained on."
)
@click.option(
    "--fit-image-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    show_default=True,
    help="Resize the full-on views by this factor for fitting (rendering always uses the source size).",
)
@click.option("--all-frames", is_flag=True, help="Expand every full-on frame, not only the first.")
@workers_option("Parallel subjects.")
@executor_option()
@device_option()
@seed_option("Seed of every subject's task.")
@click.option(
    "--lightings-per-pass",
    type=click.IntRange(min=1),
    default=16,
    show_default=True,
    help="Lightings splatted together per camera (lower it if a large render runs out of memory).",
)
@dry_run_option("Print the plan (subjects, avatar kind, image count); write nothing.")
def expand_command(
    source: Path,
    stage1: Path,
    stage2: Path,
    parent: Path,
    name: str | None,
    subjects: tuple[str, ...] | None,
    splits: tuple[str, ...] | None,
    envmaps: tuple[Path, ...],
    fit_iterations: tuple[int, int],
    fit_image_scale: float,
    all_frames: bool,
    workers: int,
    executor: str,
    device: str,
    seed: int,
    lightings_per_pass: int,
    dry_run: bool,
) -> None:
    """Relight every subject of the flat-lit dataset SOURCE under every light of the OLAT rig (and
    optional environment maps) with a trained stage-1 + stage-2 model, writing a normalized dataset of
    kind synthetic-olat. Re-running resumes: finished subjects are kept, an up-to-date output is left as is.
    """
    from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion

    plan = plan_expansion(
        source,
        stage1,
        stage2,
        parent,
        name=name,
        subjects=subjects,
        splits=splits,
        envmaps=list(envmaps),
        fit_iterations=fit_iterations,
        fit_image_scale=fit_image_scale,
        all_frames=all_frames,
        device=device,
        seed=seed,
        lightings_per_pass=lightings_per_pass,
    )
    if dry_run:
        click.echo(json.dumps(plan.summary(), indent=2))
        return
    report = expand_dataset(plan, workers=workers, executor=executor, progress=True)
    if report["up_to_date"]:
        click.echo(f"{report['output']}: up to date (same inputs and settings); nothing to do")
        return
    counts, kept = report["counts"], len(report["skipped_tasks"])
    click.echo(
        f"wrote {report['output']}: {counts['images']} images of {counts['subjects']} subjects, "
        f"{counts['patterns']} patterns, {counts['lights']} lights"
        + (f" ({kept} subject{'s' if kept != 1 else ''} kept from an earlier run)" if kept else "")
    )
