"""``relightanyone synth`` and ``relightanyone synth-preview``.

The world generator (NumPy, OpenCV) is imported inside the commands so that ``relightanyone --help`` stays
instant. synth imports nothing of the rest of the project, so it declares its options itself; its
expected failures are :class:`~relightanyone.synth.errors.WorldError`, which the command line reports as
one line.
"""

from __future__ import annotations

from pathlib import Path

import click

from relightanyone.synth.errors import WorldError

DATASET_CHOICES = ("d1", "d2", "d3", "d4")
PREVIEW_TILE_HEIGHT = 192
PREVIEW_VIEWS = 5


def _parse_datasets(value: str) -> tuple[str, ...]:
    datasets = tuple(part.strip() for part in value.split(",") if part.strip())
    unknown = [d for d in datasets if d not in DATASET_CHOICES]
    if unknown or not datasets:
        raise click.BadParameter(
            f"expected a comma-separated subset of {','.join(DATASET_CHOICES)}, got {value!r}",
            param_hint="--datasets",
        )
    return datasets


@click.command("synth")
@click.option(
    "--preset",
    type=click.Choice(["tiny", "demo", "reference", "paper"]),
    default="tiny",
    show_default=True,
    help="World size: tiny (tests, seconds), demo (laptop, minutes), reference (demo with 5 test and 2 "
    "validation subjects per dataset), paper (real counts; not for a CPU).",
)
@click.option(
    "--out",
    "out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder to write the world into (native datasets, tracking/, answers/, world.json).",
)
@click.option(
    "--seed", type=int, default=0, show_default=True, help="World seed: same seed and preset, same bytes."
)
@click.option(
    "--datasets",
    default="d1,d2,d3,d4",
    show_default=True,
    help="Comma-separated datasets to write: d1 FaceOLAT, d2 Ava-256, d3 stereo rig, d4 NeRSemble.",
)
@click.option("--overwrite", is_flag=True, help="Replace the world already in --out.")
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Processes generating datasets side by side [default: up to 2, one per CPU]; output is identical.",
)
def synth_command(
    preset: str, out: Path, seed: int, datasets: str, overwrite: bool, workers: int | None
) -> None:
    """Write a synthetic ground-truth world: four native datasets, VHAP tracking and the answers."""
    import os

    from relightanyone.synth.world import generate_world

    chosen = _parse_datasets(datasets)
    workers = workers or max(1, min(2, os.cpu_count() or 1))
    # The command line's progress report (a bar on a terminal, lines in a log) when it provides one: synth
    # imports nothing of the project, so it takes the report from the click context.
    progress = click.get_current_context().meta.get("relightanyone.progress", True)
    world = generate_world(
        out, preset, seed=seed, datasets=chosen, progress=progress, overwrite=overwrite, workers=workers
    )
    click.echo(f"wrote {preset} world (seed {seed}) with {', '.join(world['datasets'])} to {out}")
    click.echo(f"preview it with: relightanyone synth-preview {out} --out {out / 'contact-sheet.png'}")


def _label(tile, text: str):
    import cv2

    tile = tile.copy()
    cv2.rectangle(tile, (0, 0), (tile.shape[1], 16), (0, 0, 0), thickness=-1)
    cv2.putText(tile, text[:28], (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def _fit_height(image, height: int):
    import cv2

    scale = height / image.shape[0]
    width = max(1, int(round(image.shape[1] * scale)))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)


def _generic_preview(native_root: Path, count: int):
    """Any images under a native folder (EXR tone-mapped, AVIF/PNG/JPEG as display-encoded)."""
    import numpy as np
    from PIL import Image

    from relightanyone.synth.capture import srgb_encode, to_uint8
    from relightanyone.synth.envmap import read_exr

    paths = sorted(p for p in native_root.rglob("*") if p.suffix.lower() in {".exr", ".avif", ".png", ".jpg"})
    views = []
    for path in paths[:: max(1, len(paths) // max(count, 1))][:count]:
        if path.suffix.lower() == ".exr":
            linear = read_exr(path)
            scale = max(float(np.percentile(linear, 99.5)), 1e-6)
            image = to_uint8(srgb_encode(linear / scale * 0.9))
        else:
            image = np.asarray(Image.open(path).convert("RGB"))
        views.append((path.relative_to(native_root).as_posix()[-28:], image))
    return views


def build_contact_sheet(world: Path, views_per_dataset: int = PREVIEW_VIEWS):
    """(H, W, 3) uint8 sheet: one labelled row of decoded native views per dataset of the world."""
    import json

    import numpy as np

    from relightanyone.synth.world import NATIVE_DIRS, dataset_module

    description = json.loads((world / "world.json").read_text())
    rows = []
    for dataset in description["datasets"]:
        native_root = world / NATIVE_DIRS[dataset]
        module = dataset_module(dataset)
        reader = getattr(module, "preview_images", None)
        views = (
            reader(native_root, views_per_dataset)
            if reader
            else _generic_preview(native_root, views_per_dataset)
        )
        if not views:
            continue
        tiles = [
            _label(_fit_height(image, PREVIEW_TILE_HEIGHT), f"{dataset} {label}") for label, image in views
        ]
        rows.append(np.concatenate(tiles, axis=1))
    if not rows:
        raise WorldError(f"{world}: no decodable images found in the world's native folders")
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=32) for r in rows]
    return np.concatenate(rows, axis=0)


@click.command("synth-preview")
@click.argument("world", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "--out",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="PNG file to write the contact sheet to.",
)
@click.option("--views", default=PREVIEW_VIEWS, show_default=True, help="Views per dataset.")
def synth_preview_command(world: Path, out: Path, views: int) -> None:
    """Contact sheet of a synthetic world: a few views of each dataset, decoded from the native files."""
    from PIL import Image

    if not (world / "world.json").is_file():
        raise WorldError(f"{world} has no world.json; create a world with `relightanyone synth` first")
    sheet = build_contact_sheet(world, views)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(sheet).save(out)
    click.echo(f"wrote {out} ({sheet.shape[1]}x{sheet.shape[0]})")


COMMANDS: dict[str, click.Command] = {"synth": synth_command, "synth-preview": synth_preview_command}
