"""The ``relightanyone report`` command (registered by the pipelines layer as ``report_command``).

The report builder (image codecs, OpenCV) is imported inside the command so that ``relightanyone --help``
stays instant.
"""

from __future__ import annotations

from pathlib import Path

import click

from relightanyone.cli_options import ANY_PATH, out_option, parsed_by, quiet_option


def parse_titled(value: str) -> tuple[str, Path]:
    """``"Title=path"`` -> (title, path); a bare existing path takes its file name (without suffix) as title."""
    if Path(value).exists() or "=" not in value:
        path = Path(value)
        return path.stem or path.name or value, path
    title, path = value.split("=", 1)
    if not title.strip() or not path.strip():
        raise ValueError(f"{value!r}: expected TITLE=PATH")
    return title.strip(), Path(path.strip())


def titled_paths(values: tuple[str, ...]) -> list[tuple[str, Path]]:
    """Every value of a repeated ``TITLE=PATH`` option, parsed."""
    return [parse_titled(value) for value in values]


@click.command("report")
@out_option("Folder to write index.html and assets/ into (other files there are left alone).")
@click.option(
    "--datasets",
    multiple=True,
    type=ANY_PATH,
    help="Folder of normalized datasets (one per sub-folder) or one dataset folder (repeatable).",
)
@click.option(
    "--image",
    "images",
    multiple=True,
    metavar="TITLE=PATH",
    callback=parsed_by(titled_paths),
    help="A picture to show (contact sheet, world preview, ...); PNG/JPEG/WebP/GIF/AVIF, or EXR/HDR "
    "tone-mapped to sRGB (repeatable).",
)
@click.option(
    "--lighting-grid",
    type=ANY_PATH,
    help="The lighting-alignment grid of a stage-1 run (lighting_grid.png from render-stage1).",
)
@click.option(
    "--expanded",
    multiple=True,
    type=ANY_PATH,
    help="An expanded (synthetic-olat) dataset: one OLAT contact sheet per subject (repeatable).",
)
@click.option(
    "--strip",
    "strips",
    multiple=True,
    metavar="TITLE=PATH",
    callback=parsed_by(titled_paths),
    help="An environment-map relighting strip: a PNG sheet, an animated WebP/GIF, or a folder of them "
    "(repeatable).",
)
@click.option(
    "--evaluation",
    type=ANY_PATH,
    help="Evaluation folder with report.md, evaluation.json and grids/*.png.",
)
@click.option(
    "--metrics",
    multiple=True,
    metavar="TITLE=PATH",
    callback=parsed_by(titled_paths),
    help="A JSON file of stage metrics (e.g. a stage-1 run's metrics.json) shown as tables (repeatable).",
)
@click.option("--title", default="relightanyone report", show_default=True, help="Page title.")
@click.option(
    "--max-subjects",
    type=click.IntRange(min=1),
    default=24,
    show_default=True,
    help="Most subjects per dataset drawn in subject and OLAT sheets.",
)
@click.option("--olat-camera", help="Camera of the OLAT sheets (default: the middle camera of each subject).")
@click.option(
    "--no-subject-sheets", is_flag=True, help="Skip the one-view-per-subject sheet of each dataset."
)
@click.option(
    "--check",
    is_flag=True,
    help="Open the page in headless Chromium afterwards and fail unless every image loads.",
)
@quiet_option()
def report_command(
    out: Path,
    datasets: tuple[Path, ...],
    images: list[tuple[str, Path]],
    lighting_grid: Path | None,
    expanded: tuple[Path, ...],
    strips: list[tuple[str, Path]],
    evaluation: Path | None,
    metrics: list[tuple[str, Path]],
    title: str,
    max_subjects: int,
    olat_camera: str | None,
    no_subject_sheets: bool,
    check: bool,
    quiet: bool,
) -> None:
    """Write one self-contained HTML report (OUT/index.html + OUT/assets/) of datasets, pictures,
    OLAT sheets of expanded datasets, relighting strips, the evaluation and stage metrics.

    Every input is optional: what is missing shows as a "not produced" note in the page and a warning
    here. The folder uses relative links only, so it can be zipped and opened anywhere.
    """
    import warnings

    from relightanyone.pipelines.report.build import ReportInputs, ReportWarning, build_report

    inputs = ReportInputs(
        datasets=list(datasets),
        pictures=images,
        lighting_grid=lighting_grid,
        expanded=list(expanded),
        strips=strips,
        evaluation=evaluation,
        metrics=metrics,
        title=title,
        subject_sheets=not no_subject_sheets,
        max_subjects=max_subjects,
        olat_camera=olat_camera,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReportWarning)  # echoed below, once each
        result = build_report(inputs, out, progress=not quiet)
    for message in result.warnings:
        click.secho(f"warning: {message}", fg="yellow", err=True)
    click.echo(f"wrote {result.index} ({result.images} image(s), {len(result.warnings)} warning(s))")
    if check:
        from relightanyone.pipelines.report.browser import check_in_browser

        seen = check_in_browser(result.index)
        if not seen.ok:
            raise click.ClickException(
                f"{result.index}: {seen.loaded} of {seen.total} image(s) loaded in Chromium; missing: "
                f"{', '.join(seen.missing)}"
            )
        click.echo(f"checked in Chromium: all {seen.total} image(s) load")
