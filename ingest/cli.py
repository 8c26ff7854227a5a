"""``relightanyone ingest {faceolat,ava256,stereo-rig,nersemble,custom} SRC --tracking DIR --out DIR``.

Adapters are imported when their command runs, so ``relightanyone --help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path

import click

from relightanyone.ingest.registry import ADAPTERS, AdapterSpec, load_adapter

PRESETS = ("tiny", "demo", "small", "paper")


def _names(values: tuple[str, ...]) -> tuple[str, ...] | None:
    """``--subjects a,b --subjects c`` -> ("a", "b", "c"); nothing given -> None (keep everything)."""
    names = tuple(n.strip() for value in values for n in value.split(",") if n.strip())
    return names or None


def _frames(values: tuple[str, ...]) -> tuple[int, ...] | None:
    names = _names(values)
    if names is None:
        return None
    try:
        return tuple(int(n) for n in names)
    except ValueError:
        raise click.BadParameter(
            f"frames must be integers, got {', '.join(names)}", param_hint="--frames"
        ) from None


def _test_subjects(listed: tuple[str, ...], splits_file: Path | None) -> tuple[str, ...]:
    """Held-out subjects from ``--test-subjects`` and a ``--splits`` JSON ({subject: "train" | "test"})."""
    names = set(_names(listed) or ())
    if splits_file is not None:
        import json

        try:
            splits = json.loads(splits_file.read_text())
        except (OSError, ValueError) as error:
            raise click.BadParameter(f"{splits_file}: {error}", param_hint="--splits") from None
        if not isinstance(splits, dict) or not all(isinstance(v, str) for v in splits.values()):
            raise click.BadParameter(
                f'{splits_file}: expected a JSON object {{"subject": "train" | "test"}}',
                param_hint="--splits",
            )
        names |= {subject for subject, split in splits.items() if split == "test"}
    return tuple(sorted(names))


def _adapter_command(spec: AdapterSpec) -> click.Command:
    command_name, tracking_required = spec.command, spec.tracking_required

    @click.command(command_name)
    @click.argument("src", type=click.Path(exists=True, file_okay=False, path_type=Path))
    @click.option(
        "--tracking",
        type=click.Path(exists=True, file_okay=False, path_type=Path),
        required=tracking_required,
        help="VHAP export holding <subject>/transforms.json and meshes/"
        + ("" if tracking_required else " (default: the capture's own meshes/)"),
    )
    @click.option(
        "--out",
        type=click.Path(file_okay=False, path_type=Path),
        required=True,
        help="Root folder of normalized datasets; the dataset is written to OUT/<name>.",
    )
    @click.option(
        "--preset",
        type=click.Choice(PRESETS),
        default="paper",
        show_default=True,
        help="Crop size: tiny/demo 128, small 512, paper 1024.",
    )
    @click.option("--name", default=None, help="Name of the normalized dataset (default: the adapter's).")
    @click.option(
        "--template",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        default=None,
        help="Template OBJ of the tracking topology (default: template.obj next to the tracking).",
    )
    @click.option("--subjects", multiple=True, help="Subjects to keep (comma-separated or repeated).")
    @click.option("--cameras", multiple=True, help="Cameras to keep (comma-separated or repeated).")
    @click.option(
        "--frames", multiple=True, help="Native frame numbers to keep (comma-separated or repeated)."
    )
    @click.option("--test-subjects", multiple=True, help="Subjects written with split 'test'.")
    @click.option(
        "--splits",
        "splits_file",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        default=None,
        help='JSON {"subject": "train"|"test"} of a published protocol; its test subjects are held out.',
    )
    @click.option(
        "--all-frames", is_flag=True, help="Every listed frame instead of the neutral one (Ava-256)."
    )
    @click.option("--sequence", default=None, help="Sequence to read (NeRSemble; default: the first).")
    @click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True)
    @click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True)
    @click.option(
        "--dry-run", is_flag=True, help="Print what was found and the estimated size, write nothing."
    )
    def command(
        src,
        tracking,
        out,
        preset,
        name,
        template,
        subjects,
        cameras,
        frames,
        test_subjects,
        splits_file,
        all_frames,
        sequence,
        workers,
        executor,
        dry_run,
    ):
        from relightanyone.ingest.records import AdapterOptions, LayoutError
        from relightanyone.ingest.runner import found_lines, ingest_dataset, prepare
        from relightanyone.ingest.tracking import AlignmentError

        adapter = load_adapter(command_name)
        options = AdapterOptions(
            dataset_name=name,
            subjects=_names(subjects),
            cameras=_names(cameras),
            frames=_frames(frames),
            test_subjects=_test_subjects(test_subjects, splits_file),
            all_frames=all_frames,
            sequence=sequence,
        )
        try:
            adapter.detect(src)
            if executor == "local" and not dry_run:
                from relightanyone.ingest.executors import warm_local_pool

                # After the cheap layout check (a wrong SRC fails at once, with no pool to wait for), so the
                # workers' imports overlap the planning.
                warm_local_pool(workers)
            plan = adapter.plan(src, options)
            prepared = prepare(plan, tracking, preset, template, workers=workers, executor=executor)
        except (LayoutError, FileNotFoundError, ValueError) as error:
            raise click.ClickException(str(error)) from None
        for line in found_lines(plan, prepared[0], prepared[2]):
            click.echo(line)
        if dry_run:
            click.echo("dry run: nothing written")
            return
        try:
            summary = ingest_dataset(
                plan,
                tracking,
                out,
                preset,
                workers=workers,
                executor=executor,
                progress=True,
                prepared=prepared,
            )
        except AlignmentError as error:  # raised before anything is written (the rig cannot be placed)
            raise click.ClickException(str(error)) from None
        for line in summary.lines():
            click.echo(line)

    command.help = (
        f"{spec.description[0].upper()}{spec.description[1:]}.\n\n"
        f"Normalize a {command_name} capture at SRC into OUT/<name> (decode, colour calibration, canonical "
        "cameras, undistort, crop around the tracked mesh, mask, shards). Re-running resumes an interrupted run."
    )
    return command


@click.group("ingest")
def ingest_group() -> None:
    """Normalize native capture datasets into the normalized format."""


for _spec in ADAPTERS.values():
    ingest_group.add_command(_adapter_command(_spec))

COMMANDS: dict[str, click.Command] = {"ingest": ingest_group}
