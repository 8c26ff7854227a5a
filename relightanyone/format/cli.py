"""Commands of the format layer: ``validate`` and ``inspect``.

OpenCV and the dataset reader are imported inside the commands so that ``relightanyone --help`` stays
instant.
"""

from __future__ import annotations

from pathlib import Path

import click

from relightanyone.cli_options import EXISTING_FOLDER, FILE, out_option


@click.command("validate")
@click.argument("path", type=EXISTING_FOLDER)
@click.option(
    "--no-decode", is_flag=True, help="Skip decoding every image and mask (hashes and metadata only)."
)
def validate_command(path: Path, no_decode: bool) -> None:
    """Check the normalized dataset(s) in PATH (one dataset folder or a root of several).

    Prints every problem with its file and row; exits with status 1 when there is any.
    """
    from relightanyone.format.validate import validate_path

    problems = validate_path(path, decode=not no_decode, progress=True)
    for problem in problems:
        click.echo(str(problem))
    if problems:
        click.echo(
            f"{len(problems)} problem(s) in {path}; re-run the stage that wrote the dataset to repair it",
            err=True,
        )
        raise SystemExit(1)
    click.echo(f"{path}: OK")


def _summary_lines(dataset) -> list[str]:
    manifest = dataset.manifest
    files = [*manifest.shards, manifest.index, *(e for e in (manifest.meshes, manifest.lights) if e)]
    return [
        f"dataset {manifest.info.name}  kind={manifest.info.kind}  template={manifest.info.template_mesh_id}",
        f"  lighting: {manifest.info.lighting}",
        f"  rows {len(dataset)}  shards {len(manifest.shards)}  bytes {sum(e.bytes for e in files):,}",
        f"  subjects ({len(dataset.subjects)}): {', '.join(dataset.subjects[:12])}",
        f"  cameras ({len(dataset.cameras)}): {', '.join(dataset.cameras[:12])}",
        f"  patterns ({len(dataset.patterns)}): {', '.join(dataset.patterns[:12])}",
        "  splits: " + ", ".join(f"{s}={len(dataset.select(splits=s))}" for s in dataset.splits),
        f"  meshes {manifest.counts.get('meshes', 0)}  lights {manifest.counts.get('lights', 0)}  "
        f"quarantined {manifest.quarantined}",
    ]


@click.command("inspect")
@click.argument("path", type=EXISTING_FOLDER)
@out_option("Write a PNG contact sheet of sample images with mask outlines here.", file=True, required=False)
@click.option(
    "--samples",
    type=click.IntRange(1, 256),
    default=16,
    show_default=True,
    help="Number of images on the contact sheet (spread evenly over the keys of all datasets).",
)
@click.option(
    "--overlay",
    type=FILE,
    default=None,
    help="Write a PNG of the tracked mesh reprojected over sample images (datasets written by ingest).",
)
def inspect_command(path: Path, out: Path | None, samples: int, overlay: Path | None) -> None:
    """Summarize the normalized dataset(s) in PATH and optionally draw a contact sheet."""
    import cv2
    import numpy as np

    from relightanyone.format.preview import render_contact_sheet
    from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
    from relightanyone.format.shards import dataset_dirs
    from relightanyone.progress import progress_bar

    datasets = []
    for dataset_dir in dataset_dirs(path):
        try:
            datasets.append(NormalizedDataset(dataset_dir))
        except IncompleteDatasetError as error:
            click.echo(f"skipping {dataset_dir}: {error}", err=True)
    if not datasets:
        raise click.ClickException(
            f"{path} holds no complete dataset; run `relightanyone validate {path}` for details"
        )
    for dataset in datasets:
        click.echo("\n".join(_summary_lines(dataset)))
    if overlay is not None:
        _write_overlay(datasets, overlay, samples)
    if out is None:
        return
    picks = [(d, k) for d in datasets for k in d.keys]
    if not picks:
        raise click.ClickException(f"{path} has no image rows to draw")
    chosen = [
        picks[i] for i in sorted(set(np.linspace(0, len(picks) - 1, min(samples, len(picks))).astype(int)))
    ]
    images, masks, labels = [], [], []
    for dataset, key in progress_bar(chosen, desc="contact sheet", unit="image"):
        row, image, mask = dataset.decoded(key)
        images.append(image)
        masks.append(mask)
        labels.append(f"{row.dataset}/{row.subject} {row.camera} {row.pattern}")
    sheet = render_contact_sheet(images, masks, labels)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet[..., ::-1]):
        raise click.ClickException(
            f"could not write {out}; check the folder is writable and the name ends in .png"
        )
    click.echo(f"contact sheet: {out}")


def _write_overlay(datasets: list, out: Path, samples: int) -> None:
    """Reprojection overlays (``relightanyone.format.overlay``), one row of samples per dataset."""
    import cv2
    import numpy as np

    from relightanyone.format.overlay import reprojection_overlays

    rows = []
    for dataset in datasets:
        try:
            tiles = reprojection_overlays(dataset.path, samples=min(samples, 8))
        except (FileNotFoundError, KeyError) as error:
            click.echo(f"no overlay for {dataset.path}: {error}", err=True)
            continue
        if not tiles:
            click.echo(f"no overlay for {dataset.path}: it has no image rows to draw", err=True)
            continue
        side = max(t.shape[0] for t in tiles)
        tiles = [cv2.resize(t, (side, side), interpolation=cv2.INTER_AREA) for t in tiles]
        rows.append(
            np.concatenate(tiles + [np.zeros_like(tiles[0])] * (min(samples, 8) - len(tiles)), axis=1)
        )
    if not rows:
        raise click.ClickException(
            "no overlay to draw: no dataset in PATH has image rows with their template.obj and meshes.arrow"
        )
    width = max(r.shape[1] for r in rows)
    sheet = np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], axis=0)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet[..., ::-1]):
        raise click.ClickException(
            f"could not write {out}; check the folder is writable and the name ends in .png"
        )
    click.echo(f"reprojection overlay: {out}")


COMMANDS: dict[str, click.Command] = {"validate": validate_command, "inspect": inspect_command}
