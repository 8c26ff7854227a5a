"""``relightanyone ingest {faceolat,ava256,stereo-rig,nersemble,custom} SRC --tracking DIR --out DIR``.

Adapters, the runner and its executors are imported when a command runs (they pull in OpenCV and the
decoders), so ``relightanyone --help`` stays fast.
"""

from __future__ import annotations

import click

from relightanyone.cli_options import (
    EXISTING_FILE,
    EXISTING_FOLDER,
    comma_separated,
    dry_run_option,
    executor_option,
    names_option,
    out_option,
    parsed_by,
    preset_option,
    workers_option,
)
from relightanyone.errors import InputError
from relightanyone.ingest.records import AdapterOptions, published_splits
from relightanyone.ingest.registry import ADAPTERS, AdapterSpec, load_adapter


def frame_numbers(values: tuple[str, ...]) -> tuple[int, ...] | None:
    """``--frames 3,7 --frames 9`` -> (3, 7, 9); nothing given -> None (keep every frame)."""
    names = comma_separated(values)
    if names is None:
        return None
    try:
        return tuple(int(n) for n in names)
    except ValueError:
        raise ValueError(f"frames must be integers, got {', '.join(names)}") from None


def sensor_size(value: str | None) -> tuple[int, int] | None:
    """``--sensor-size 2668x4096`` -> (2668, 4096); nothing given -> None (the layout's own)."""
    if value is None:
        return None
    parts = value.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ValueError(
            f"sensor size must be WIDTHxHEIGHT in pixels, e.g. 2668x4096, got {value!r}"
        ) from None
    if width <= 0 or height <= 0:
        raise ValueError(f"sensor size must be positive, got {value!r}")
    return width, height


def accept_check_option() -> click.Option:
    return click.option(
        "--accept-check",
        "accepted_checks",
        multiple=True,
        metavar="NAME",
        help="Do not apply this convention check (repeatable; the names are listed in docs/ingest.md, "
        "Checks); recorded in the manifest.",
    )


def _adapter_command(spec: AdapterSpec, doctor: bool = False) -> click.Command:
    """``ingest <layout>``, or with ``doctor`` ``doctor <layout>`` (same arguments, only the checks)."""
    command_name, tracking_required = spec.command, spec.tracking_required

    @click.command(command_name)
    @click.argument("src", type=EXISTING_FOLDER)
    @click.option(
        "--tracking",
        type=EXISTING_FOLDER,
        required=tracking_required,
        help="VHAP export holding <subject>/transforms.json and meshes/"
        + ("" if tracking_required else " (default: the capture's own meshes/)"),
    )
    @out_option(
        "Root folder of normalized datasets; the dataset is written to OUT/<name>.", required=not doctor
    )
    @preset_option("paper", "Crop size: tiny/demo 128, small 512, paper 1024.")
    @click.option("--name", default=None, help="Name of the normalized dataset (default: the adapter's).")
    @click.option(
        "--template",
        type=EXISTING_FILE,
        default=None,
        help="Template OBJ of the tracking topology (default: template.obj next to the tracking).",
    )
    @names_option("--subjects", "Subjects to keep (comma-separated or repeated).")
    @names_option("--cameras", "Cameras to keep (comma-separated or repeated).")
    @click.option(
        "--frames",
        multiple=True,
        metavar="N,M",
        callback=parsed_by(frame_numbers),
        help="Native frame numbers to keep (comma-separated or repeated).",
    )
    @names_option("--test-subjects", "Subjects written with split 'test'.")
    @click.option(
        "--splits",
        "splits_file",
        type=EXISTING_FILE,
        default=None,
        help='JSON {"subject": "train"|"val"|"test"} of a published protocol: each row gets its '
        "subject's split (unlisted subjects train); training reads only 'train' rows.",
    )
    @click.option(
        "--all-frames", is_flag=True, help="Every listed frame instead of the neutral one (Ava-256)."
    )
    @click.option("--sequence", default=None, help="Sequence to read (NeRSemble; default: the first).")
    @click.option(
        "--sensor-size",
        default=None,
        metavar="WxH",
        callback=parsed_by(sensor_size),
        help="Size in pixels of the sensor the calibration's K describes, when it is not the layout's "
        "own (Ava-256: 2668x4096; NeRSemble: the file's width/height or 2200x3208).",
    )
    @click.option(
        "--tracking-fps",
        type=click.FloatRange(min=0, min_open=True),
        default=None,
        help="Frame rate the tracked frames were extracted at (VHAP's default is 25), when the tracking "
        "does not match the capture's video frame for frame.",
    )
    @click.option(
        "--no-neck-mask",
        is_flag=True,
        help="Accept a template without its neck_mask.txt: masks and crops then include the neck "
        "(recorded in the manifest).",
    )
    @workers_option()
    @executor_option()
    @dry_run_option("Print what was found and the estimated size, write nothing.")
    @accept_check_option()
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
        sensor_size,
        tracking_fps,
        no_neck_mask,
        workers,
        executor,
        dry_run,
        accepted_checks,
    ):
        from relightanyone.ingest.runner import (
            alignment_failures,
            check_lines,
            found_lines,
            ingest_dataset,
            ingest_executor,
            nothing_to_write,
            planning_reasons,
            prepare,
            run_checks,
        )
        from relightanyone.ingest.tracking import TrackingOptions  # imports torch through the calibration

        adapter = load_adapter(command_name)
        published = published_splits(splits_file) if splits_file else {}
        held_out = set(test_subjects or ()) | {s for s, split in published.items() if split == "test"}
        options = AdapterOptions(
            dataset_name=name,
            subjects=subjects,
            cameras=cameras,
            frames=frames,
            test_subjects=tuple(sorted(held_out)),
            val_subjects=tuple(sorted(s for s, split in published.items() if split == "val")),
            all_frames=all_frames,
            sequence=sequence,
            sensor_size=sensor_size,
        )
        adapter.detect(src)
        if not (dry_run or doctor):
            # After the cheap layout check (a wrong SRC fails at once, with no pool to wait for), so the
            # workers' imports overlap the planning.
            ingest_executor(workers, executor).warm()
        plan = adapter.plan(src, options)
        unmatched = options.unmatched()
        if unmatched:
            raise InputError(f"{src}: {'; '.join(unmatched)}")
        tracking_options = TrackingOptions(tracking_fps=tracking_fps, no_neck_mask=no_neck_mask)
        prepared = prepare(
            plan,
            tracking,
            preset,
            template,
            workers=workers,
            executor=executor,
            tracking_options=tracking_options,
        )
        for line in found_lines(plan, prepared[0], prepared[2], every_reason=dry_run):
            click.echo(line)
        empty = nothing_to_write(plan, prepared[2])
        if empty:
            raise InputError(empty)
        # doctor judges every image, a dry run the first frame of each subject, the ingest each image it
        # writes (inside its tasks).
        image_frames = None if doctor else 1 if dry_run else 0
        checks = run_checks(prepared, tuple(accepted_checks), image_frames)
        for line in check_lines(checks, images_later=not (doctor or dry_run)):
            click.echo(line)
        checks.raise_for_stops(str(src), listed=True)
        if doctor or dry_run:
            click.echo("dry run: nothing written" if dry_run else "doctor: nothing written")
            refused = len(planning_reasons(plan)) + len(alignment_failures(prepared[2]))
            if doctor and (checks.findings or refused):
                # Anything the ingest would refuse fails the command, so a script can gate an ingest on a
                # clean doctor run.
                if refused:
                    click.echo(f"doctor: {refused} items refused while planning or aligning (listed above)")
                click.get_current_context().exit(1)
            return
        summary = ingest_dataset(
            plan,
            tracking,
            out,
            preset,
            workers=workers,
            executor=executor,
            progress=True,
            prepared=prepared,
            checks=checks,
        )
        for line in summary.lines():
            click.echo(line)

    command.help = (
        f"{spec.description[0].upper()}{spec.description[1:]}.\n\n"
        f"Normalize a {command_name} capture at SRC into OUT/<name> (decode, colour calibration, canonical "
        "cameras, undistort, crop around the tracked mesh, mask, shards). Re-running resumes an interrupted run."
    )
    if doctor:
        command.help = (
            f"Check a {command_name} capture at SRC for convention mistakes (cameras, units, images) with the "
            "arguments ingest takes, reading every image once; write nothing. Exits 1 on anything the ingest would refuse: a dataset-level "
            "mistake, views it would quarantine, or items refused while planning or aligning."
        )
    return command


@click.group("ingest")
def ingest_group() -> None:
    """Normalize native capture datasets into the normalized format."""


@click.group("doctor")
def doctor_group() -> None:
    """Check a native capture for camera, unit and image mistakes before ingesting it."""


for _spec in ADAPTERS.values():
    ingest_group.add_command(_adapter_command(_spec))
    doctor_group.add_command(_adapter_command(_spec, doctor=True))

COMMANDS: dict[str, click.Command] = {"ingest": ingest_group, "doctor": doctor_group}
