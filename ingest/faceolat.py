"""FaceOLAT / 3DPR light-stage captures (D1, OLAT) -> a :class:`DatasetPlan`.

Layout read (the output of FaceOLAT's processing scripts, ``docs/ingest.md``)::

    calibration/cameras/{subject}.xml                    Metashape camera XML, one per subject
    color-calibration/colorcalib_exr.mat                 text 4x4: [M | black], last row 0 0 0 1
    relighting/lights/light_pattern_metadata.json        Goliath schema: light positions (mm), patterns
    relighting/lights/light_pattern_per_frame.json       nominal [[frame, pattern], ...] schedule
    {subject}/lights/{capture}/light_pattern_per_frame.json   the schedule this take used (preferred)
    {subject}/OutputEXR/{camera}/{capture}/{capture}.{frame:06d}.exr    linear RGB
    {subject}/OutputAVIF/{camera}/{capture}/{capture}.{frame:06d}.avif  gamma-2.2, colour already applied

Frames may also sit in a shared ``OutputEXR/`` (or ``OutputAVIF/``) at the root, with capture ids
``ID{g}0{subject}`` telling which subject they belong to.

Conventions: pattern 0 of the schedule is full-on (every light), pattern k >= 1 is light k - 1 alone
(Goliath); a light's intensity is its duration in its OLAT pattern / 5555. Which frames are full-on comes
from the take's schedule, never from a fixed list (real takes are shifted by one frame). Light positions
are millimetres in the calibration's world, so the plan carries them in metres of that world. Cameras
without calibration are refused with Metashape's reason, not guessed.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relightanyone.align.colour import read_faceolat_colour_matrix
from relightanyone.format.schema import check_name
from relightanyone.ingest.adapter_common import adapter_plan
from relightanyone.ingest.calibration import CalibrationError, downsample_factor, loads_json
from relightanyone.ingest.decode import header_size
from relightanyone.ingest.metashape import read_metashape_xml
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

NAME = "faceolat"
KIND = "olat"
SOURCE_DATASET = "FaceOLAT"
LICENCE = "FaceOLAT terms: academic and research use only (gvv-assets.mpi-inf.mpg.de/FaceOLAT)"

CAMERAS_DIR = "calibration/cameras"
COLOUR_FILE = "color-calibration/colorcalib_exr.mat"
LIGHT_METADATA = "relighting/lights/light_pattern_metadata.json"
NOMINAL_SCHEDULE = "relighting/lights/light_pattern_per_frame.json"
TAKE_SCHEDULE = "{subject}/lights/{capture}/light_pattern_per_frame.json"
DURATION_UNIT = 5555.0  # Goliath: a light's intensity is its duration / 5555
# Frame numbers of a subject's k-th capture start at k * 1000 (takes have 350 frames), so keys stay unique.
FRAMES_PER_CAPTURE = 1000
# Frame folders in order of preference: linear EXR beats the 8-bit AVIF export.
FRAME_FORMATS = (("OutputEXR", ".exr", "exr-linear"), ("OutputAVIF", ".avif", "avif-gamma22"))
_FRAME_FILE = re.compile(r"^(?P<capture>.+)\.(?P<frame>\d{6})\.(?:exr|avif)$")


@dataclass(frozen=True)
class LightRig:
    """The light stage's lights and patterns from ``light_pattern_metadata.json``.

    Attributes:
        positions_mm: (L, 3) light positions in millimetres of the calibration world.
        olat_durations: (L,) duration of each light in the pattern that lights it alone.
        full_durations: (L,) duration of each light in pattern 0 (full-on).
        pattern_names: the file's pattern names, in order (index = pattern number).
    """

    positions_mm: np.ndarray
    olat_durations: np.ndarray
    full_durations: np.ndarray
    pattern_names: tuple[str, ...]

    @property
    def intensities(self) -> np.ndarray:
        """(L, 3) linear RGB intensity of each light during its OLAT frame (duration / 5555, white)."""
        return np.repeat((self.olat_durations / DURATION_UNIT)[:, None], 3, axis=1)

    @property
    def full_on_intensities(self) -> np.ndarray:
        """(L, 3) intensity of each light during the full-on frames (its pattern-0 duration / 5555)."""
        return np.repeat((self.full_durations / DURATION_UNIT)[:, None], 3, axis=1)


def _load_json(path: Path, what: str):
    try:
        return loads_json(path.read_text())
    except FileNotFoundError:
        raise LayoutError(f"{path}: {what} not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise LayoutError(f"{path}: {what} is not valid JSON ({error})") from None


def read_light_metadata(path: str | Path) -> LightRig:
    """Read a Goliath-style ``light_pattern_metadata.json``; checks the full-on/OLAT pattern convention.

    Pattern 0 must light every light (full-on) and pattern k >= 1 exactly light k - 1. Raises ValueError
    naming the file and the field on anything else.
    """
    path = Path(path)
    data = _load_json(path, "light pattern metadata")
    if not isinstance(data, dict) or "light_positions" not in data or "light_patterns" not in data:
        raise LayoutError(f"{path}: expected an object with 'light_positions' and 'light_patterns'")
    try:
        positions = np.asarray(data["light_positions"], dtype=np.float64)
    except (TypeError, ValueError):
        raise LayoutError(f"{path}: field 'light_positions' is not a list of [x, y, z]") from None
    if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) == 0:
        raise LayoutError(f"{path}: field 'light_positions' must be (L, 3), got shape {positions.shape}")
    if not np.isfinite(positions).all():
        raise LayoutError(f"{path}: field 'light_positions' contains NaN or infinity")
    count = len(positions)
    patterns = data["light_patterns"]
    if not isinstance(patterns, list) or len(patterns) != count + 1:
        found = len(patterns) if isinstance(patterns, list) else type(patterns).__name__
        raise LayoutError(
            f"{path}: field 'light_patterns' must hold {count + 1} patterns (full + one per light), got {found}"
        )
    durations = []
    for index, pattern in enumerate(patterns):
        field = f"light_patterns[{index}].light_index_durations"
        try:
            pairs = np.asarray(pattern["light_index_durations"], dtype=np.float64).reshape(-1, 2)
        except (TypeError, ValueError, KeyError):
            raise LayoutError(
                f"{path}: field '{field}' is missing or not a list of [light, duration]"
            ) from None
        if not np.isfinite(pairs).all() or (pairs[:, 1] <= 0).any():
            raise LayoutError(f"{path}: field '{field}' needs finite positive durations")
        durations.append(pairs)
    full = durations[0]
    if sorted(full[:, 0].astype(int).tolist()) != list(range(count)):
        raise LayoutError(f"{path}: pattern 0 must be full-on (light every one of the {count} lights once)")
    full_durations = np.zeros(count)
    full_durations[full[:, 0].astype(int)] = full[:, 1]
    olat_durations = np.zeros(count)
    for k in range(1, count + 1):
        pairs = durations[k]
        if len(pairs) != 1 or int(pairs[0, 0]) != k - 1:
            raise LayoutError(
                f"{path}: pattern {k} must light light {k - 1} alone (OLAT k -> light k-1), got lights "
                f"{pairs[:, 0].astype(int).tolist()}"
            )
        olat_durations[k - 1] = pairs[0, 1]
    names = tuple(
        str(p.get("name", f"pattern {i}")) if isinstance(p, dict) else f"pattern {i}"
        for i, p in enumerate(patterns)
    )
    return LightRig(positions, olat_durations, full_durations, names)


def read_pattern_schedule(path: str | Path, pattern_count: int) -> dict[int, int]:
    """Read ``light_pattern_per_frame.json`` (``[[frame, pattern], ...]``) into ``{frame: pattern}``.

    Raises ValueError naming the file when an entry is malformed, a frame repeats or a pattern is not in
    ``0 .. pattern_count - 1``.
    """
    path = Path(path)
    data = _load_json(path, "light pattern schedule")
    if not isinstance(data, list) or not data:
        raise LayoutError(f"{path}: expected a non-empty list of [frame, pattern] pairs")
    schedule: dict[int, int] = {}
    for index, entry in enumerate(data):
        if (
            not isinstance(entry, list)
            or len(entry) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in entry)
        ):
            raise LayoutError(f"{path}: entry {index} must be [frame, pattern] integers, got {entry!r}")
        frame, pattern = entry
        if frame in schedule:
            raise LayoutError(f"{path}: frame {frame} is listed twice (entry {index})")
        if not 0 <= pattern < pattern_count:
            raise LayoutError(f"{path}: entry {index}: pattern {pattern} is not in 0..{pattern_count - 1}")
        schedule[frame] = pattern
    return schedule


def pattern_name(pattern: int) -> str:
    """Row pattern name of schedule pattern ``pattern``: 0 -> "full", k -> "olat-{k-1:03d}"."""
    return "full" if pattern == 0 else f"olat-{pattern - 1:03d}"


def full_on_frames(schedule: dict[int, int]) -> list[int]:
    """Sorted frames whose pattern is 0 (full-on)."""
    return sorted(frame for frame, pattern in schedule.items() if pattern == 0)


def _frame_roots(src: Path) -> list[tuple[Path, str, str]]:
    """(root, extension, codec) of every frame folder, per subject folder or shared at the top."""
    roots = []
    for folder, ext, codec in FRAME_FORMATS:
        for candidate in [src / folder, *sorted(src.glob(f"*/{folder}"))]:
            if candidate.is_dir():
                roots.append((candidate, ext, codec))
    return roots


def detect(src: Path) -> str:
    """Layout version: ``"processed-exr"`` or ``"processed-avif"`` (EXR wins when both are present).

    Raises LayoutError naming the first missing piece.
    """
    src = Path(src)
    if not src.is_dir():
        raise LayoutError(f"{src}: FaceOLAT folder not found")
    if not sorted((src / CAMERAS_DIR).glob("*.xml")):
        raise LayoutError(f"{src / CAMERAS_DIR}: no Metashape camera XML (<subject>.xml) found")
    for required, what in ((COLOUR_FILE, "colour matrix"), (LIGHT_METADATA, "light pattern metadata")):
        if not (src / required).is_file():
            raise LayoutError(f"{src / required}: FaceOLAT {what} not found")
    roots = _frame_roots(src)
    if not roots:
        raise LayoutError(
            f"{src}: no frames found (expected <subject>/OutputEXR/<camera>/<capture>/ or OutputAVIF/)"
        )
    return "processed-exr" if roots[0][2] == "exr-linear" else "processed-avif"


def _subject_of_capture(capture: str) -> str | None:
    """FaceOLAT capture ids are ``ID{group}0{subject:03d}``; returns the subject or None."""
    match = re.fullmatch(r"ID\d0(\d{3})", capture)
    return match.group(1) if match else None


def _scan_frames(src: Path, ext: str) -> dict[str, dict[str, dict[str, dict[int, Path]]]]:
    """{subject: {capture: {camera: {frame: path}}}} of every frame file with extension ``ext``."""
    found: dict[str, dict[str, dict[str, dict[int, Path]]]] = {}
    folder = next(name for name, e, _ in FRAME_FORMATS if e == ext)
    for root in [src / folder, *sorted(src.glob(f"*/{folder}"))]:
        if not root.is_dir():
            continue
        owner = None if root.parent == src else check_name(root.parent.name, "subject", str(root.parent))
        for camera_dir in sorted(p for p in root.iterdir() if p.is_dir()):
            for capture_dir in sorted(p for p in camera_dir.iterdir() if p.is_dir()):
                subject = owner or _subject_of_capture(capture_dir.name)
                if subject is None:
                    continue
                frames = (
                    found.setdefault(subject, {})
                    .setdefault(capture_dir.name, {})
                    .setdefault(camera_dir.name, {})
                )
                with os.scandir(capture_dir) as entries:
                    for entry in entries:
                        match = _FRAME_FILE.match(entry.name)
                        if match and entry.name.endswith(ext) and match.group("capture") == capture_dir.name:
                            frames[int(match.group("frame"))] = Path(entry.path)
    return found


def _camera_image_sizes(
    captures: dict[str, dict[str, dict[int, Path]]], cameras: tuple[str, ...], codec: str
) -> dict[str, tuple[int, int]]:
    """Stored size of each camera's frames, from the first frame whose header reads."""
    sizes: dict[str, tuple[int, int]] = {}
    for capture_frames in captures.values():
        for camera, frames in capture_frames.items():
            for frame in sorted(frames):
                if camera in sizes or camera not in cameras:
                    break
                size = header_size(frames[frame], codec)
                if size is not None:
                    sizes[camera] = size
    return sizes


def _native_cameras(
    rig, image_sizes: dict[str, tuple[int, int]]
) -> tuple[dict[str, NativeCamera], dict[str, str]]:
    """NativeCamera per calibrated camera, K rescaled (half-pixel rule) to the frames' size.

    Returns (cameras, problems): a camera whose frames have another aspect ratio than its calibration
    is a problem, not a camera.
    """
    cameras, problems = {}, {}
    for index, name in enumerate(rig.cameras.names):
        one = rig.cameras[index]
        width, height = int(one.width[0]), int(one.height[0])
        K = one.K[0].numpy().astype(np.float64)
        if name in image_sizes and image_sizes[name] != (width, height):
            try:  # the calibration's sensor size against the frames'; the rig's principal points check it
                downscale = downsample_factor(rig.cameras.K.numpy(), image_sizes[name], (width, height))
            except ValueError as error:
                problems[name] = f"frames do not fit the calibration of camera {name}: {error}"
                continue
            K = downscale.intrinsics(K)
            width, height = image_sizes[name]
        cameras[name] = NativeCamera(
            name=name,
            K=K,
            w2c=one.w2c[0].numpy().astype(np.float64),
            dist=one.dist[0, :5].numpy().astype(np.float64),
            width=width,
            height=height,
        )
    return cameras, problems


def _colour(src: Path, codec: str) -> ColourCalibration:
    """FaceOLAT's matrix for linear EXR; the AVIF export has it applied already (exr2avif.py's default)."""

    path = src / COLOUR_FILE
    try:
        M, black = read_faceolat_colour_matrix(path)
    except FileNotFoundError as error:
        raise LayoutError(str(error)) from None
    if codec == "exr-linear":
        return ColourCalibration(matrix=M, black=black, space="linear", source=COLOUR_FILE)
    return ColourCalibration(matrix=np.eye(3), source=f"{COLOUR_FILE} (applied by the AVIF export)")


def _take_schedule(src: Path, subject: str, capture: str, pattern_count: int) -> tuple[dict[int, int], str]:
    """The take's own schedule when it has one, else the rig's nominal schedule; with its relative path."""
    own = TAKE_SCHEDULE.format(subject=subject, capture=capture)
    relative = own if (src / own).is_file() else NOMINAL_SCHEDULE
    return read_pattern_schedule(src / relative, pattern_count), relative


def _plan_subject(
    src: Path,
    subject: str,
    captures: dict[str, dict[str, dict[int, Path]]],
    codec: str,
    colour: ColourCalibration,
    pattern_count: int,
    options: AdapterOptions,
    found: dict,
) -> SubjectPlan:
    """Views and refusals of one subject (all its captures)."""

    plan = SubjectPlan(subject=subject, split=options.split_of(subject), views=[])
    xml = f"{CAMERAS_DIR}/{subject}.xml"
    if not (src / xml).is_file():
        plan.refusals.append(Refusal(subject, xml, f"no calibration file {xml} for subject {subject}"))
        return plan
    try:
        rig = read_metashape_xml(src / xml)
    except CalibrationError as error:
        plan.refusals.append(Refusal(subject, xml, str(error)))
        return plan
    for camera, reason in sorted(rig.missing.items()):
        if options.keeps_camera(camera):
            plan.refusals.append(Refusal(f"{subject}/{camera}", xml, f"camera not calibrated: {reason}"))

    # A camera whose frames have no readable header keeps its calibrated size; the runner quarantines
    # the unreadable frames when it decodes them.
    cameras, problems = _native_cameras(rig, _camera_image_sizes(captures, rig.cameras.names, codec))
    for camera, reason in sorted(problems.items()):
        plan.refusals.append(Refusal(f"{subject}/{camera}", xml, reason))
    plan.rig_w2c = {
        name: rig.cameras.w2c[i].numpy().astype(np.float64) for i, name in enumerate(rig.cameras.names)
    }

    schedules = found.setdefault("schedules", {})
    for rank, capture in enumerate(sorted(captures)):
        try:
            schedule, schedule_file = _take_schedule(src, subject, capture, pattern_count)
        except (ValueError, LayoutError) as error:
            plan.refusals.append(
                Refusal(
                    f"{subject}/{capture}", TAKE_SCHEDULE.format(subject=subject, capture=capture), str(error)
                )
            )
            continue
        schedules[f"{subject}/{capture}"] = {
            "file": schedule_file,
            "full_on_frames": full_on_frames(schedule),
        }
        for camera, frames in sorted(captures[capture].items()):
            if not options.keeps_camera(camera) or camera in problems or camera in rig.missing:
                continue
            item = f"{subject}/{capture}/{camera}"
            if camera not in cameras:
                plan.refusals.append(
                    Refusal(item, xml, f"camera {camera} has frames but is absent from {xml}")
                )
                continue
            for frame in sorted(set(frames) | set(schedule)):
                stored_frame = rank * FRAMES_PER_CAPTURE + frame
                if not options.keeps_frame(stored_frame):
                    continue
                if frame not in frames:
                    plan.refusals.append(
                        Refusal(
                            f"{item}/{frame:06d}",
                            schedule_file,
                            "frame listed in the light schedule is missing",
                        )
                    )
                    continue
                source = frames[frame].relative_to(src).as_posix()
                if frame not in schedule:
                    plan.refusals.append(
                        Refusal(
                            f"{item}/{frame:06d}", source, f"frame has no light pattern in {schedule_file}"
                        )
                    )
                    continue
                plan.views.append(
                    SourceView(
                        subject=subject,
                        frame=stored_frame,
                        camera=cameras[camera],
                        pattern=pattern_name(schedule[frame]),
                        image=ImageRef(path=str(frames[frame]), codec=codec),
                        colour=colour,
                        source=source,
                    )
                )
    return plan


def plan(src: Path, options: AdapterOptions) -> DatasetPlan:
    """Describe every usable frame of a FaceOLAT folder; see the module docstring for the layout.

    Raises LayoutError / ValueError naming the file for dataset-wide problems (missing or corrupt colour
    matrix or light metadata); per-subject, per-camera and per-frame problems become Refusals.
    """
    src = Path(src).resolve()
    version = detect(src)
    roots = _frame_roots(src)
    codec, ext = roots[0][2], next(e for _, e, c in FRAME_FORMATS if c == roots[0][2])
    colour = _colour(src, codec)
    lights = read_light_metadata(src / LIGHT_METADATA)
    frames = _scan_frames(src, ext)
    calibrated = {p.stem for p in (src / CAMERAS_DIR).glob("*.xml")}
    found: dict = {
        "layout": version,
        "codec": codec,
        "lights": len(lights.positions_mm),
        "full_on_duration_per_light": lights.full_durations.tolist(),
        "subjects_with_frames": sorted(frames),
        "calibrated_subjects_without_frames": sorted(calibrated - set(frames)),
    }
    subjects = []
    for subject in sorted(frames):
        if options.keeps_subject(subject):
            subjects.append(
                _plan_subject(
                    src, subject, frames[subject], codec, colour, len(lights.pattern_names), options, found
                )
            )
    found["views"] = sum(len(s.views) for s in subjects)
    found["cameras"] = sorted({v.camera.name for s in subjects for v in s.views})
    return adapter_plan(
        NAME,
        KIND,
        SOURCE_DATASET,
        LICENCE,
        version,
        src,
        options,
        subjects,
        light_positions=lights.positions_mm * 1e-3,
        light_intensities=lights.intensities,
        full_on_light_intensities=lights.full_on_intensities,
        found=found,
    )
