"""Ava-256 captures (D2, flat-lit) -> a :class:`DatasetPlan`.

Layout read (the Ava-256 release, ``docs/ingest.md``; one capture = one subject)::

    {mcd}--{mct}--{sid}/decoder/                 (or the DATASHEET name m--{mcd}--{mct}--{sid}--GHS)
        camera_calibration.json                  {"KRT": [...]}: K and w2c stored transposed, mm
        frame_list.csv                           seg_id,frame_id
        head_pose/head_pose.zip                  {frame:06d}.txt: 3x4 head -> world, mm
        image/cam{id}.zip                        members cam{id}/{frame:06d}.avif

``SRC`` is either one capture folder or a folder holding several.

Conventions:

* Cameras: ``read_krt_json`` (transposes, mm -> m). K describes the full 2668x4096 sensor (or
  ``--sensor-size``) while the images are a downscale of it: the factor comes from the stored image size
  against the sensor size on both axes (``ingest.calibration.downsample_factor``; the principal points,
  off-centre on the real rig, only check it), and K is resized to the stored size with the half-pixel
  rule. The image size is read from the first readable member of each camera's zip (header only).
* The native->tracker fit uses every calibrated camera (``SubjectPlan.rig_w2c``), whatever ``--cameras``
  keeps and whatever images a frame lacks.
* Each frame's head pose is folded into the extrinsics (``align.geometry.fold_head_pose``), so a view's
  native world is the capture's head space in metres: the head never moves.
* Frames: the ``EXP_neutral_peak`` rows of ``frame_list.csv`` by default; every listed frame with
  ``AdapterOptions.all_frames``; ``AdapterOptions.frames`` picks listed frames by id.
* Images hold linear values as 8-bit codes (no transfer curve; ava-256#32), codec ``avif-linear``.
  No colour calibration file exists: the identity is recorded and the model learns a 3x3 later.
* A frame listed in ``frame_list.csv`` whose member is absent from a camera's zip (a dropped frame), an
  unreadable zip, a camera without a zip or without calibration, and a frame without a usable head pose
  are refused, not guessed.
"""

from __future__ import annotations

import csv
import io
import re
import zipfile
from pathlib import Path, PurePosixPath

import numpy as np

from relightanyone.align.geometry import fold_head_pose
from relightanyone.format.schema import check_name
from relightanyone.ingest.adapter_common import adapter_plan, root_relative
from relightanyone.ingest.calibration import (
    AVA_FULL_SENSOR,
    CalibrationError,
    Downscale,
    downsample_factor,
    read_krt_json,
)
from relightanyone.ingest.records import (
    AdapterOptions,
    ColourCalibration,
    DatasetPlan,
    ImageRef,
    LayoutError,
    NativeCamera,
    Refusal,
    SourceView,
    SubjectPlan,
)

NAME = "ava256"
KIND = "flat"
SOURCE_DATASET = "Ava-256"
LICENCE = "CC BY-NC 4.0 (Meta Codec Avatar Studio, ava-256)"
LAYOUT_VERSION = "decoder-zip"

CALIBRATION = "decoder/camera_calibration.json"
FRAME_LIST = "decoder/frame_list.csv"
HEAD_POSE_ZIP = "decoder/head_pose/head_pose.zip"
IMAGE_DIR = "decoder/image"
NEUTRAL_SEGMENT = "EXP_neutral_peak"
CODEC = "avif-linear"


def capture_folders(src: Path) -> list[Path]:
    """Capture folders under ``src`` (``src`` itself when it holds ``decoder/``), sorted by name."""
    src = Path(src)
    if (src / "decoder").is_dir():
        return [src]
    return sorted(p.parent for p in src.glob("*/decoder") if p.is_dir())


def subject_of(capture: Path) -> str:
    """Subject id of a capture folder: ``{mcd}--{mct}--{sid}`` or ``m--{mcd}--{mct}--{sid}--GHS`` -> sid."""
    parts = capture.name.split("--")
    subject = parts[3] if parts[0] == "m" and len(parts) >= 4 else parts[-1]
    return check_name(subject, "subject", str(capture))


def detect(src: Path) -> str:
    """Layout version (``"decoder-zip"``); raises LayoutError naming what is missing."""
    src = Path(src)
    if not src.is_dir():
        raise LayoutError(f"{src}: Ava-256 folder not found")
    captures = capture_folders(src)
    if not captures:
        raise LayoutError(
            f"{src}: no capture found (expected {src}/decoder/ or {src}/<mcd>--<mct>--<sid>/decoder/)"
        )
    for capture in captures:
        if (capture / CALIBRATION).is_file() and (capture / IMAGE_DIR).is_dir():
            return LAYOUT_VERSION
    first = captures[0]
    missing = CALIBRATION if not (first / CALIBRATION).is_file() else IMAGE_DIR
    raise LayoutError(f"{first / missing}: not found (no capture has both {CALIBRATION} and {IMAGE_DIR}/)")


def read_frame_list(path: Path) -> list[tuple[str, int]]:
    """``[(seg_id, frame_id), ...]`` from ``frame_list.csv``; ValueError naming the file when malformed."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise LayoutError(f"{path}: frame list not found") from None
    rows = list(csv.DictReader(io.StringIO(text)))
    if not rows or not {"seg_id", "frame_id"} <= set(rows[0]):
        raise LayoutError(f"{path}: expected a header 'seg_id,frame_id' and at least one row")
    out = []
    for line, row in enumerate(rows, start=2):
        try:
            out.append((row["seg_id"], int(row["frame_id"])))
        except (TypeError, ValueError):
            raise LayoutError(
                f"{path}: line {line}: frame_id {row.get('frame_id')!r} is not an integer"
            ) from None
    return out


def select_frames(listed: list[tuple[str, int]], options: AdapterOptions) -> list[int]:
    """Frames to ingest: ``options.frames`` (listed ones), every frame, or the neutral peak (default)."""
    if options.frames is not None:
        return sorted({f for _, f in listed if f in options.frames})
    if options.all_frames:
        return sorted({f for _, f in listed})
    return sorted({f for seg, f in listed if seg == NEUTRAL_SEGMENT})


def read_head_poses(path: Path, frames: list[int]) -> tuple[dict[int, np.ndarray], dict[int, str]]:
    """Head->world (4, 4), in metres, per frame; and the reason for each frame without a usable pose."""
    poses, problems = {}, {}
    try:
        archive = zipfile.ZipFile(path)
    except FileNotFoundError:
        return {}, {f: f"head pose archive {path.name} not found" for f in frames}
    except (zipfile.BadZipFile, OSError) as error:
        return {}, {f: f"head pose archive {path.name} is unreadable ({error})" for f in frames}
    with archive:
        names = set(archive.namelist())
        for frame in frames:
            member = f"{frame:06d}.txt"
            if member not in names:
                problems[frame] = f"no head pose {member} in {path.name}"
                continue
            try:
                values = np.loadtxt(io.BytesIO(archive.read(member)), dtype=np.float64, ndmin=2)
            except (ValueError, zipfile.BadZipFile, OSError) as error:
                problems[frame] = f"head pose {member} is unreadable ({error})"
                continue
            if values.shape != (3, 4) or not np.isfinite(values).all():
                problems[frame] = f"head pose {member} must be a finite 3x4 matrix, got shape {values.shape}"
                continue
            R = values[:, :3]
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) <= 0:
                problems[frame] = f"head pose {member} is not a rigid transform"
                continue
            pose = np.eye(4)
            pose[:3, :3] = R
            pose[:3, 3] = values[:, 3] * 1e-3  # mm -> m
            poses[frame] = pose
    return poses, problems


def _safe_member(name: str) -> bool:
    path = PurePosixPath(name)
    return not path.is_absolute() and ".." not in path.parts and "\\" not in name


def _scan_camera_zip(path: Path) -> tuple[dict[int, str], tuple[int, int] | None, list[str]]:
    """{frame: member}, the image size (from the first readable member) and unsafe member names."""
    from PIL import Image

    members, unsafe, size = {}, [], None
    with zipfile.ZipFile(path) as archive:
        for name in archive.namelist():
            if not _safe_member(name):
                unsafe.append(name)
                continue
            match = re.fullmatch(r"cam[^/]+/(\d{6})\.avif", name)
            if match:
                members[int(match.group(1))] = name
        for frame in sorted(members):
            try:
                with Image.open(io.BytesIO(archive.read(members[frame]))) as image:
                    size = image.size
                break
            except (OSError, ValueError, zipfile.BadZipFile):
                continue  # the runner refuses that image when it decodes it; the next one gives the size
    return members, size, unsafe


def _plan_capture(capture: Path, root: Path, options: AdapterOptions) -> SubjectPlan:
    """Views and refusals of one capture folder."""
    subject = subject_of(capture)
    plan = SubjectPlan(subject=subject, split=options.split_of(subject), views=[])
    relpath = root_relative(capture, root)

    try:
        rig = read_krt_json(capture / CALIBRATION, units="mm")
    except CalibrationError as error:
        plan.refusals.append(Refusal(subject, relpath(CALIBRATION), str(error)))
        return plan
    try:
        listed = read_frame_list(capture / FRAME_LIST)
    except ValueError as error:  # LayoutError (missing file) is a ValueError too
        plan.refusals.append(Refusal(subject, relpath(FRAME_LIST), str(error)))
        return plan
    frames = select_frames(listed, options)
    if not frames:
        plan.refusals.append(
            Refusal(
                subject,
                relpath(FRAME_LIST),
                f"no frame selected (no {NEUTRAL_SEGMENT} rows or none of --frames)",
            )
        )
        return plan
    poses, pose_problems = read_head_poses(capture / HEAD_POSE_ZIP, frames)
    for frame, reason in sorted(pose_problems.items()):
        plan.refusals.append(Refusal(f"{subject}/{frame:06d}", relpath(HEAD_POSE_ZIP), reason))

    calibrated = set(rig.names)
    zips = {p.stem[3:]: p for p in sorted((capture / IMAGE_DIR).glob("cam*.zip"))}
    for camera in sorted(set(zips) - calibrated):
        if options.keeps_camera(camera):
            plan.refusals.append(
                Refusal(
                    f"{subject}/{camera}",
                    relpath(f"{IMAGE_DIR}/cam{camera}.zip"),
                    f"camera {camera} is absent from {CALIBRATION}",
                )
            )
    scans = {}
    for index, camera in enumerate(rig.names):
        if not options.keeps_camera(camera):
            continue
        source = relpath(f"{IMAGE_DIR}/cam{camera}.zip")
        if camera not in zips:
            plan.refusals.append(Refusal(f"{subject}/{camera}", source, f"no image archive cam{camera}.zip"))
            continue
        try:
            members, size, unsafe = _scan_camera_zip(zips[camera])
        except (zipfile.BadZipFile, OSError) as error:
            plan.refusals.append(Refusal(f"{subject}/{camera}", source, f"unreadable zip archive ({error})"))
            continue
        for name in unsafe:
            plan.refusals.append(
                Refusal(f"{subject}/{camera}/{name}", source, "member name leaves the archive (unsafe path)")
            )
        if size is None:
            plan.refusals.append(Refusal(f"{subject}/{camera}", source, "no readable image in the archive"))
            continue
        scans[index] = (camera, members, size)
    if not scans:
        return plan

    plan.rig_w2c = {name: rig.w2c[i].numpy().astype(np.float64) for i, name in enumerate(rig.names)}
    plan.head_poses = poses
    sensor = options.sensor_size or AVA_FULL_SENSOR
    downscales: dict[tuple[int, int], Downscale] = {}
    colour = ColourCalibration.identity()
    for index, (camera, members, size) in scans.items():
        one = rig[index]
        if size not in downscales:
            try:  # the principal points of the whole rig check the factor of every image size
                downscales[size] = downsample_factor(rig.K.numpy(), size, sensor)
            except ValueError as error:
                plan.refusals.append(
                    Refusal(f"{subject}/{camera}", relpath(f"{IMAGE_DIR}/cam{camera}.zip"), str(error))
                )
                continue
        downscale = downscales[size]
        K, w2c_world, dist = (
            downscale.intrinsics(one.K[0].numpy()),
            one.w2c[0].numpy(),
            one.dist[0, :5].numpy(),
        )
        source = relpath(f"{IMAGE_DIR}/cam{camera}.zip")
        for frame in frames:
            if not options.keeps_frame(frame) or frame not in poses:
                continue
            member = f"cam{camera}/{frame:06d}.avif"
            if frame not in members:
                plan.refusals.append(
                    Refusal(
                        f"{subject}/{camera}/{frame:06d}",
                        f"{source}::{member}",
                        "dropped frame: listed in frame_list.csv but absent from the archive",
                    )
                )
                continue
            native = NativeCamera(
                camera, K.copy(), fold_head_pose(w2c_world, poses[frame]), dist.copy(), size[0], size[1]
            )
            plan.views.append(
                SourceView(
                    subject=subject,
                    frame=frame,
                    camera=native,
                    pattern="full",
                    image=ImageRef(path=str(zips[camera]), codec=CODEC, member=members[frame]),
                    colour=colour,
                    source=f"{source}::{members[frame]}",
                )
            )
    plan.found["downscale"] = sorted(
        f"{d.image[0]}x{d.image[1]} = {d.sensor[0]}x{d.sensor[1]} sensor / {d.factor:g}"
        for d in downscales.values()
    )
    return plan


def plan(src: Path, options: AdapterOptions) -> DatasetPlan:
    """Describe the selected frames of every Ava-256 capture under ``src`` (see the module docstring).

    Per-capture, per-camera and per-frame problems become Refusals; a folder that is no Ava-256 layout
    raises LayoutError.
    """
    src = Path(src).resolve()
    version = detect(src)
    captures = [c for c in capture_folders(src) if options.keeps_subject(subject_of(c))]
    subjects, refusals = [], []
    seen: dict[str, Path] = {}
    for capture in captures:
        subject = subject_of(capture)
        if subject in seen:  # two captures of one person would share frame keys; keep the first
            refusals.append(
                Refusal(
                    capture.name,
                    capture.name,
                    f"second capture of subject {subject} (first: {seen[subject].name})",
                )
            )
            continue
        seen[subject] = capture
        subjects.append(_plan_capture(capture, src, options))
    found = {
        "layout": version,
        "captures": [c.name for c in captures],
        "cameras": sorted({v.camera.name for s in subjects for v in s.views}),
        "frames": {s.subject: sorted({v.frame for v in s.views}) for s in subjects},
        "views": sum(len(s.views) for s in subjects),
        "image_size (downscale)": sorted({d for s in subjects for d in s.found.get("downscale", [])}),
        "frame_selection": "listed ids"
        if options.frames is not None
        else ("all" if options.all_frames else NEUTRAL_SEGMENT),
    }
    return adapter_plan(
        NAME, KIND, SOURCE_DATASET, LICENCE, version, src, options, subjects, refusals=refusals, found=found
    )
