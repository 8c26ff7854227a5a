"""Commands of the pipelines layer: ``run`` (a pipeline file), ``export-dataset``, ``report`` and ``expand``.

The runner, the exporter (OpenEXR) and the model load inside the commands so that ``relightanyone --help``
stays instant.
"""

from __future__ import annotations

from pathlib import Path

import click

from relightanyone.cli_options import EXISTING_FOLDER, dry_run_option, names_option, out_option, quiet_option
from relightanyone.errors import InputError
from relightanyone.os_errors import check_writable
from relightanyone.pipelines.expand.command import expand_command
from relightanyone.pipelines.report.command import report_command

SHIPPED_PIPELINES = ("demo", "real")


def _pipeline_path(value: str) -> Path:
    """A pipeline file, or the name of one shipped with the package (``demo``, ``real``)."""
    path = Path(value)
    if path.is_file():
        return path
    if value in SHIPPED_PIPELINES:
        return Path(__file__).resolve().parent / f"{value}.yaml"
    raise InputError(f"{value}: no such pipeline file (shipped pipelines: {', '.join(SHIPPED_PIPELINES)})")


def _summary(results) -> list[str]:
    width = max(len(r.stage) for r in results)
    lines = [f"{'stage'.ljust(width)}  {'status':<12}  {'elapsed':>8}  reason"]
    for result in results:
        elapsed = f"{result.elapsed_s:7.1f}s" if result.status == "ran" else "       -"
        lines.append(f"{result.stage.ljust(width)}  {result.status:<12}  {elapsed:>8}  {result.reason}")
    return lines


@click.command("run")
@click.argument("pipeline", metavar="PIPELINE")
@click.option(
    "--var",
    "variables",
    multiple=True,
    metavar="NAME=VALUE",
    help="Override a variable of the file's vars: section (repeatable), e.g. --var out=/scratch/demo.",
)
@click.option(
    "--force",
    multiple=True,
    metavar="STAGE",
    help="Re-run this stage and everything downstream of it, even when up to date (repeatable).",
)
@click.option(
    "--only",
    multiple=True,
    metavar="STAGE",
    help="Run only these stages (repeatable); the stages they need must have completed before.",
)
@dry_run_option(
    "Print which stages would run or be skipped, and why, and each training stage's estimated peak "
    "memory per GPU; run nothing."
)
@quiet_option("Do not stream the stages' own output (it is still in _stage.log).")
def run_command(
    pipeline: str,
    variables: tuple[str, ...],
    force: tuple[str, ...],
    only: tuple[str, ...],
    dry_run: bool,
    quiet: bool,
) -> None:
    """Run the staged pipeline in PIPELINE (a YAML file, or `demo` / `real` for the shipped ones).

    Each stage writes OUTPUT/_stage.json when it succeeds and is skipped next time unless its config,
    an input, the package version or its output files changed. An interrupted run is finished by running
    the same command again. See docs/pipelines.md for the file format.
    """
    import sys

    from relightanyone.pipelines.dag.memory import stage_memory
    from relightanyone.pipelines.dag.pipeline_file import parse_var_overrides
    from relightanyone.pipelines.dag.runner import execute, load_pipeline, plan

    loaded = load_pipeline(_pipeline_path(pipeline), parse_var_overrides(variables))
    if dry_run:
        decisions = plan(loaded, force=force, only=only)
        width = max(len(d.stage) for d in decisions)
        for decision in decisions:
            action = (
                "stop" if decision.reason.startswith("cannot run") else "run " if decision.run else "skip"
            )
            click.echo(f"{action}  {decision.stage.ljust(width)}  {decision.reason}")
            memory = stage_memory(loaded.stages[decision.stage]) if decision.run else None
            if memory:
                click.echo(f"      {' ' * width}  memory: {memory}")
        click.echo(f"dry run: {sum(d.run for d in decisions)} of {len(decisions)} stage(s) would run")
        blocked = [d.stage for d in decisions if d.reason.startswith("cannot run")]
        if blocked:
            raise click.ClickException(f"stage(s) {', '.join(blocked)} would stop the run: fix their inputs")
        return
    for stage in loaded.stages.values():  # an unwritable output stops the run before any stage starts
        check_writable(stage.output)
    results = execute(
        loaded,
        force=force,
        only=only,
        echo=None if quiet else sys.stdout.buffer,
        announce=lambda line: click.secho(line, bold=True),
    )
    click.echo("\n".join(_summary(results)))


@click.command("export-dataset")
@click.argument("dataset", type=EXISTING_FOLDER)
@click.option(
    "--format",
    "file_format",
    type=click.Choice(["exr"]),
    default="exr",
    show_default=True,
    help="Image file format (linear OpenEXR).",
)
@out_option("Folder to write <subject>/<frame>/<camera>/<pattern>.exr, masks and the JSON tables into.")
@click.option(
    "--precision",
    type=click.Choice(["float", "half"]),
    default="float",
    show_default=True,
    help="EXR pixel type: float keeps the decoded values exactly, half halves the size.",
)
@names_option("--subjects", "Subjects to export (comma-separated or repeated; default all).")
def export_dataset_command(
    dataset: Path, file_format: str, out: Path, precision: str, subjects: tuple[str, ...] | None
) -> None:
    """Write the normalized dataset DATASET as linear EXR images, mask PNGs, cameras.json and lights.json.

    For tools outside this one: OUT/<subject>/<frame>/<camera>/<pattern>.exr and <pattern>.mask.png, one
    cameras.json row per image (K, w2c, size, file names) and lights.json (the rig of an OLAT dataset).
    """
    from relightanyone.pipelines.export import export_dataset

    summary = export_dataset(dataset, out, precision=precision, subjects=subjects, progress=True)
    click.echo(
        f"exported {summary['images']} image(s) of {summary['dataset']} to {out} "
        f"({summary['subjects']} subject(s), {summary['lights']} light(s))"
    )


COMMANDS: dict[str, click.Command] = {
    "export-dataset": export_dataset_command,
    "expand": expand_command,
    "report": report_command,
    "run": run_command,
}
