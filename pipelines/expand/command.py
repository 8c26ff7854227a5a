"""``relightanyone expand SOURCE_DATASET --stage1 RUN --stage2 RUN --out PARENT``: the OLAT expansion job.

Heavy imports stay inside the command so that ``relightanyone --help`` stays instant.
"""

from __future__ import annotations

from pathlib import Path

import click


def _names(values: tuple[str, ...]) -> list[str] | None:
    """``--subjects a,b --subjects c`` -> ["a", "b", "c"]; nothing given -> None (everything)."""
    names = [n.strip() for value in values for n in value.split(",") if n.strip()]
    return names or None


@click.command("expand")
@click.argument("source", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "--stage1",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    required=True,
    help="Stage-1 run folder (the one the stage-2 run was trained on).",
)
@click.option(
    "--stage2",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    required=True,
    help="Stage-2 run folder; its OLAT dataset's rig becomes the output's lights.arrow.",
)
@click.option(
    "--out",
    "parent",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Parent folder; the dataset is written to OUT/NAME and fitted avatars to OUT/NAME-avatars.",
)
@click.option("--name", default=None, help="Output dataset name (default: <source>-olat).")
@click.option(
    "--subjects", multiple=True, metavar="A,B", help="Only these subjects (repeatable or comma list)."
)
@click.option(
    "--splits", multiple=True, metavar="train,test", help="Only source rows of these splits (default: all)."
)
@click.option(
    "--envmap",
    "envmaps",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Also render under this lat-long .exr/.hdr environment map, as pattern env-<file stem> (repeatable).",
)
@click.option(
    "--fit-iterations",
    nargs=2,
    type=click.IntRange(min=0),
    default=(300, 300),
    show_default=True,
    metavar="N M",
    help="Inversion and finetuning steps for subjects the stage-1 run was not trained on.",
)
@click.option(
    "--fit-image-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    show_default=True,
    help="Resize the full-on views by this factor for fitting (rendering always uses the source size).",
)
@click.option("--all-frames", is_flag=True, help="Expand every full-on frame, not only the first.")
@click.option(
    "--workers", type=click.IntRange(min=1), default=1, show_default=True, help="Parallel subjects."
)
@click.option(
    "--executor",
    type=click.Choice(["local", "ray"]),
    default="local",
    show_default=True,
    help="Task executor.",
)
@click.option(
    "--device",
    default="auto",
    show_default=True,
    help="auto (CUDA when available, else CPU), cpu, or cuda[:N].",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every subject's task.")
@click.option(
    "--lightings-per-pass",
    type=click.IntRange(min=1),
    default=16,
    show_default=True,
    help="Lightings splatted together per camera (lower it if a large render runs out of memory).",
)
@click.option(
    "--dry-run", is_flag=True, help="Print the plan (subjects, avatar kind, image count); write nothing."
)
def expand_command(
    source: Path,
    stage1: Path,
    stage2: Path,
    parent: Path,
    name: str | None,
    subjects: tuple[str, ...],
    splits: tuple[str, ...],
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
    import json

    from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion

    try:
        plan = plan_expansion(
            source,
            stage1,
            stage2,
            parent,
            name=name,
            subjects=_names(subjects),
            splits=_names(splits),
            envmaps=list(envmaps),
            fit_iterations=fit_iterations,
            fit_image_scale=fit_image_scale,
            all_frames=all_frames,
            device=device,
            seed=seed,
            lightings_per_pass=lightings_per_pass,
        )
    except (ValueError, FileNotFoundError, KeyError) as error:
        raise click.ClickException(str(error)) from None
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
