"""NeRSemble multi-view video captures (D4, flat-lit), release v2 and v1 -> a :class:`DatasetPlan`.

Layouts read (``docs/ingest.md``; ``SRC`` is the release root holding ``{p_id:03d}/`` folders, or one)::

    v2  {p}/calibration/camera_params.json          {"world_2_cam": {serial: 4x4}, "intrinsics": 3x3 | {serial: 3x3}}
        {p}/calibration/color_calibration.json      {serial: 3x3 or 3x4 Cheung-2004 CCM}, linear light
        {p}/sequences/{SEQ}/images/cam_{serial}.mp4 one video per camera, read by frame index
        {p}/sequences/BACKGROUND/...                 clean plates, ignored
    v1  {p}/camera_params.json                      same keys
        {p}/sequences/{SEQ}/frame_{t:05d}/images-2x-73fps/cam_{serial}.png   2x downsampled
        {p}/sequences/{SEQ}/frame_{t:05d}/alpha_map-73fps/cam_{serial}.png   optional alpha maps
        {p}/annotations/{SEQ}/color_correction/{serial}.npy                  affine, display space

The version is read from the folder structure (:func:`detect`), never asked for.

Conventions:

* Cameras: ``ingest.calibration.from_nersemble_params`` (OpenCV world_2_cam, metres, no distortion).
  ``intrinsics`` describe the calibrated sensor (``--sensor-size``, else the file's ``width``/``height``
  keys, else the 2200x3208 frame), of which the stored images are a downscale (v1's PNGs are 2x smaller):
  the factor comes from the two sizes (``ingest.calibration.downsample_factor``; the principal points
  only check it) and K is resized to the stored size with the half-pixel rule.
* There is no head pose in the release: cameras stay in the capture's world and the tracked meshes
  carry the head's motion.
* Colour: v2's CCM acts on linear light after the video's sRGB decoding (codec ``mp4-frame``),
  ``ColourCalibration`` space ``"linear"``; v1's affine ``rgb @ A[:3, :3] + A[:3, 3]`` acts on the
  sRGB-encoded PNG values (row vectors, so the matrix is stored transposed), space ``"display"``.
* Sequence: ``AdapterOptions.sequence`` (its full name, or the part before the description: ``EMO-1``
  for ``EMO-1-shout+laugh``), else the one sequence other than ``BACKGROUND`` that holds images; with
  several, the participant is refused until ``--sequence`` chooses. Frames: ``AdapterOptions.frames``,
  else every frame of the sequence.
* Refused, not guessed: a participant whose calibration or colour file is missing or invalid, a camera
  without colour calibration, an unreadable video, a frame past the end of a camera's video, a missing
  PNG, a calibrated serial without a video (or PNG folder) and a video of a serial the calibration lacks.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from relightanyone.align.colour import read_nersemble_colour_calibration, read_nersemble_v1_affine
from relightanyone.format.schema import check_name
from relightanyone.ingest.adapter_common import adapter_plan, root_relative
from relightanyone.ingest.calibration import (
    NERSEMBLE_FULL_SENSOR,
    CalibrationError,
    Downscale,
    downsample_factor,
    from_nersemble_params,
    loads_json,
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

NAME = "nersemble"
KIND = "flat"
SOURCE_DATASET = "NeRSemble"
LICENCE = "NeRSemble dataset terms of use: non-commercial research, access by request (TUM)"

BACKGROUND = "BACKGROUND"
V2_CALIBRATION = "calibration/camera_params.json"
V2_COLOUR = "calibration/color_calibration.json"
V2_VIDEO = "sequences/{sequence}/images/cam_{serial}.mp4"
V1_CALIBRATION = "camera_params.json"
V1_IMAGE_DIR = "images-2x-73fps"
V1_ALPHA_DIR = "alpha_map-73fps"
V1_COLOUR = "annotations/{sequence}/color_correction/{serial}.npy"
_PARTICIPANT = re.compile(r"^\d{3,}$")
_FRAME_DIR = re.compile(r"^frame_(\d+)$")
_VIDEO = re.compile(r"^cam_(.+)\.mp4$")
_PNG = re.compile(r"^cam_(.+)\.png$")


def participant_folders(src: Path) -> list[Path]:
    """Participant folders under ``src`` (``src`` itself when it is one), sorted by name."""
    src = Path(src)
    if (src / "sequences").is_dir():
        return [src]
    return sorted(p for p in src.iterdir() if p.is_dir() and _PARTICIPANT.match(p.name))


def _version_of(folder: Path) -> str | None:
    if (folder / V2_CALIBRATION).is_file() and any((folder / "sequences").glob("*/images/cam_*.mp4")):
        return "v2"
    if (folder / V1_CALIBRATION).is_file() and any((folder / "sequences").glob(f"*/frame_*/{V1_IMAGE_DIR}")):
        return "v1"
    return None


def detect(src: Path) -> str:
    """Layout version, ``"v2"`` (videos) or ``"v1"`` (PNG frames); raises LayoutError naming what is missing."""
    src = Path(src)
    if not src.is_dir():
        raise LayoutError(f"{src}: NeRSemble folder not found")
    folders = participant_folders(src)
    if not folders:
        raise LayoutError(f"{src}: no participant folder found (expected {src}/<p_id:03d>/sequences/)")
    versions = {v for v in (_version_of(f) for f in folders) if v is not None}
    if len(versions) > 1:
        raise LayoutError(
            f"{src}: participants mix the v1 (PNG) and v2 (video) layouts; ingest them separately"
        )
    if versions:
        return versions.pop()
    first = folders[0]
    raise LayoutError(
        f"{first}: neither v2 ({V2_CALIBRATION} + sequences/<SEQ>/images/cam_<serial>.mp4) nor v1 "
        f"({V1_CALIBRATION} + sequences/<SEQ>/frame_<t>/{V1_IMAGE_DIR}/) found"
    )


def choose_sequence(folder: Path, version: str, wanted: str | None) -> tuple[str | None, str]:
    """``(the sequence to ingest, or None, why none)``: ``wanted`` by its full name or by the part before
    its description (``EMO-1`` for ``EMO-1-shout+laugh``, as tracking exports name it) when that names one
    sequence; without ``wanted``, the one non-BACKGROUND sequence holding images (several need a choice)."""
    pattern = "images/cam_*.mp4" if version == "v2" else f"frame_*/{V1_IMAGE_DIR}"
    names = sorted(
        p.name
        for p in (folder / "sequences").glob("*")
        if p.is_dir() and p.name != BACKGROUND and any(p.glob(pattern))
    )
    listed = ", ".join(names[:8]) + (f" … and {len(names) - 8} more" if len(names) > 8 else "")
    if not names:
        return None, "no sequence other than BACKGROUND holds images"
    if wanted is None:
        if len(names) == 1:
            return names[0], ""
        return None, f"{len(names)} sequences hold images ({listed}): pass --sequence NAME to choose one"
    if wanted in names:
        return wanted, ""
    matches = [n for n in names if n.startswith(f"{wanted}-")]
    if len(matches) == 1:
        return matches[0], ""
    if matches:
        return (
            None,
            f"--sequence {wanted} names {len(matches)} sequences ({', '.join(matches)}): give the full name",
        )
    return None, f"no sequence {wanted} with images (sequences: {listed})"


def video_info(path: Path) -> tuple[int, int, int, float | None]:
    """``(width, height, frame_count, frames per second)`` of a video from its container (no decoding; the
    rate is None when the container states none); ValueError if unreadable."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise LayoutError(f"{path}: holds no video stream")
            stream = container.streams.video[0]
            count = int(stream.frames)
            if count <= 0:  # containers without a frame count: count the packets (no decoding)
                count = sum(1 for packet in container.demux(stream) if packet.size)
            rate = stream.average_rate or stream.base_rate
            fps = float(rate) if rate else None
            return int(stream.codec_context.width), int(stream.codec_context.height), count, fps
    except (av.error.FFmpegError, OSError) as error:
        raise LayoutError(f"{path}: not a readable video ({error})") from None


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` from an image header; ValueError naming the file when it is unreadable."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, ValueError) as error:
        raise LayoutError(f"{path}: not a readable image ({error})") from None


def calibrated_sensor(calibration: dict, options: AdapterOptions) -> tuple[int, int]:
    """(width, height) the intrinsics describe: ``--sensor-size``, else the file's ``width``/``height``
    keys, else NeRSemble's 2200x3208 frame."""
    if options.sensor_size is not None:
        return options.sensor_size
    return (
        int(calibration.get("width", NERSEMBLE_FULL_SENSOR[0])),
        int(calibration.get("height", NERSEMBLE_FULL_SENSOR[1])),
    )


def read_rig(
    path: Path, size: tuple[int, int], options: AdapterOptions
) -> tuple[dict[str, NativeCamera], Downscale]:
    """Cameras of ``camera_params.json`` for stored images of ``size`` (width, height), by serial, and the
    downscale from the calibrated sensor (:func:`calibrated_sensor`).

    Raises ``CalibrationError``/ValueError naming the file when it is invalid.
    """
    import json

    if not Path(path).is_file():
        raise CalibrationError(path, "<file>", "calibration file not found")
    try:
        data = loads_json(Path(path).read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise CalibrationError(path, "<file>", f"not readable JSON ({error})") from None
    if not isinstance(data, dict):
        raise CalibrationError(path, "<file>", "expected a JSON object")
    rig = from_nersemble_params(path, image_size=size)  # given the path, its errors name the file
    try:
        downscale = downsample_factor(rig.K.numpy(), size, calibrated_sensor(data, options))
    except ValueError as error:
        raise CalibrationError(path, "intrinsics", str(error)) from None
    Ks = downscale.intrinsics(rig.K.numpy())
    cameras = {}
    for index, serial in enumerate(rig.names):
        K = Ks[index]
        if abs(np.linalg.det(K)) < 1e-9:
            raise CalibrationError(path, f"intrinsics ({serial})", "singular intrinsics matrix")
        cameras[serial] = NativeCamera(
            name=serial,
            K=K,
            w2c=rig.w2c[index].numpy().astype(np.float64),
            dist=np.zeros(5),
            width=size[0],
            height=size[1],
        )
    return cameras, downscale


def _v2_colour(path: Path, source: str) -> dict[str, ColourCalibration]:

    return {
        serial: ColourCalibration(matrix=M, offset=offset, space="linear", source=source)
        for serial, (M, offset) in read_nersemble_colour_calibration(path).items()
    }


def _v1_colour(path: Path, source: str) -> ColourCalibration:

    A = read_nersemble_v1_affine(path)
    # v1 multiplies row vectors (rgb @ A[:3, :3]); a ColourCalibration multiplies columns.
    return ColourCalibration(matrix=A[:, :3].T, offset=A[:, 3], space="display", source=source)


def _plan_v2(
    folder: Path, root: Path, sequence: str, options: AdapterOptions, plan: SubjectPlan, facts: dict
) -> None:

    subject = plan.subject
    relpath = root_relative(folder, root)

    videos_dir = folder / "sequences" / sequence / "images"
    videos = {m.group(1): p for p in sorted(videos_dir.glob("cam_*.mp4")) if (m := _VIDEO.match(p.name))}
    infos: dict[str, tuple[int, int, int, float | None]] = {}
    for serial, path in videos.items():
        if not options.keeps_camera(serial):
            continue
        try:
            infos[serial] = video_info(path)
        except ValueError as error:
            plan.refusals.append(
                Refusal(f"{subject}/{serial}", relpath(path.relative_to(folder).as_posix()), str(error))
            )
    if not infos:
        plan.refusals.append(
            Refusal(
                subject, relpath(f"sequences/{sequence}/images"), "no readable video of a selected camera"
            )
        )
        return
    size = infos[sorted(infos)[0]][:2]
    try:
        cameras, downscale = read_rig(folder / V2_CALIBRATION, size, options)
    except (CalibrationError, ValueError) as error:
        plan.refusals.append(Refusal(subject, relpath(V2_CALIBRATION), str(error)))
        return
    try:
        colours = _v2_colour(folder / V2_COLOUR, relpath(V2_COLOUR))
    except (ValueError, FileNotFoundError) as error:
        plan.refusals.append(Refusal(subject, relpath(V2_COLOUR), str(error)))
        return
    facts.update(image_size=list(size), downsample_factor=downscale.factor)
    plan.rig_w2c = {serial: camera.w2c for serial, camera in cameras.items()}
    for serial in sorted(set(videos) - set(cameras)):
        if options.keeps_camera(serial):
            plan.refusals.append(
                Refusal(
                    f"{subject}/{serial}",
                    relpath(V2_VIDEO.format(sequence=sequence, serial=serial)),
                    f"camera {serial} is absent from {V2_CALIBRATION}",
                )
            )
    longest = max(count for _, _, count, _ in infos.values())
    rates = sorted({fps for *_, fps in infos.values() if fps})
    plan.frame_rate, plan.frame_count = (rates[0] if len(rates) == 1 else None), longest
    if len(rates) > 1:  # the cameras disagree: no single native clock to pair the tracking with
        plan.refusals.append(
            Refusal(
                subject,
                relpath(f"sequences/{sequence}/images"),
                f"the videos run at different frame rates ({', '.join(f'{r:g}' for r in rates)} fps)",
            )
        )
        return
    facts.update(frame_rate=rates[0] if rates else None)
    frames = sorted(options.frames) if options.frames is not None else list(range(longest))
    for serial in sorted(cameras):
        if not options.keeps_camera(serial):
            continue
        source = relpath(V2_VIDEO.format(sequence=sequence, serial=serial))
        if serial not in videos:
            plan.refusals.append(
                Refusal(f"{subject}/{serial}", source, "missing video: no file for this calibrated camera")
            )
            continue
        if serial not in infos:
            continue  # unreadable video, refused above
        if serial not in colours:
            plan.refusals.append(
                Refusal(
                    f"{subject}/{serial}", relpath(V2_COLOUR), f"camera {serial} has no colour calibration"
                )
            )
            continue
        width, height, count, _ = infos[serial]
        camera = cameras[serial]
        if (width, height) != (camera.width, camera.height):
            plan.refusals.append(
                Refusal(
                    f"{subject}/{serial}",
                    source,
                    f"video is {width}x{height}, the other cameras' {camera.width}x{camera.height}",
                )
            )
            continue
        for frame in frames:
            if frame >= count or frame < 0:
                plan.refusals.append(
                    Refusal(
                        f"{subject}/{serial}/{frame:05d}",
                        f"{source}#frame={frame}",
                        f"missing frame: the video has {count} frames",
                    )
                )
                continue
            plan.views.append(
                SourceView(
                    subject=subject,
                    frame=frame,
                    camera=camera,
                    pattern="full",
                    image=ImageRef(path=str(videos[serial]), codec="mp4-frame", frame_index=frame),
                    colour=colours[serial],
                    source=f"{source}#frame={frame}",
                )
            )


def _plan_v1(
    folder: Path, root: Path, sequence: str, options: AdapterOptions, plan: SubjectPlan, facts: dict
) -> None:

    subject = plan.subject
    relpath = root_relative(folder, root)

    frame_dirs = {
        int(m.group(1)): p
        for p in sorted((folder / "sequences" / sequence).glob("frame_*"))
        if (m := _FRAME_DIR.match(p.name)) and (p / V1_IMAGE_DIR).is_dir()
    }
    frames = sorted(f for f in frame_dirs if options.keeps_frame(f))
    # v1's frame folders are the 73 fps video's frames (the image folder's name states the rate).
    plan.frame_rate = float(re.search(r"(\d+)fps", V1_IMAGE_DIR).group(1))
    plan.frame_count = max(frame_dirs, default=-1) + 1
    for frame in sorted(set(options.frames or ()) - set(frame_dirs)):
        plan.refusals.append(
            Refusal(
                f"{subject}/{frame:05d}",
                relpath(f"sequences/{sequence}/frame_{frame:05d}"),
                "missing frame: no frame folder",
            )
        )
    pngs = {
        frame: {
            m.group(1): p
            for p in sorted((frame_dirs[frame] / V1_IMAGE_DIR).glob("cam_*.png"))
            if (m := _PNG.match(p.name))
        }
        for frame in frames
    }
    serials = sorted({s for by_serial in pngs.values() for s in by_serial if options.keeps_camera(s)})
    size = None
    for frame in frames:
        for serial in serials:
            if serial in pngs[frame]:
                try:
                    size = image_size(pngs[frame][serial])
                    break
                except ValueError:
                    continue  # the runner refuses that image when it decodes it; another gives the size
        if size is not None:
            break
    if size is None:
        plan.refusals.append(
            Refusal(subject, relpath(f"sequences/{sequence}"), "no readable PNG frame of a selected camera")
        )
        return
    try:
        cameras, downscale = read_rig(folder / V1_CALIBRATION, size, options)
    except (CalibrationError, ValueError) as error:
        plan.refusals.append(Refusal(subject, relpath(V1_CALIBRATION), str(error)))
        return
    facts.update(image_size=list(size), downsample_factor=downscale.factor)
    plan.rig_w2c = {serial: camera.w2c for serial, camera in cameras.items()}
    for serial in sorted(set(serials) - set(cameras)):
        plan.refusals.append(
            Refusal(
                f"{subject}/{serial}",
                relpath(f"sequences/{sequence}"),
                f"camera {serial} is absent from {V1_CALIBRATION}",
            )
        )
    for serial in sorted(cameras):
        if not options.keeps_camera(serial):
            continue
        colour_rel = V1_COLOUR.format(sequence=sequence, serial=serial)
        try:
            colour = _v1_colour(folder / colour_rel, relpath(colour_rel))
        except ValueError as error:
            plan.refusals.append(Refusal(f"{subject}/{serial}", relpath(colour_rel), str(error)))
            continue
        for frame in frames:
            image_rel = f"sequences/{sequence}/frame_{frame:05d}/{V1_IMAGE_DIR}/cam_{serial}.png"
            if serial not in pngs[frame]:
                plan.refusals.append(
                    Refusal(
                        f"{subject}/{serial}/{frame:05d}",
                        relpath(image_rel),
                        "missing frame: no PNG for this calibrated camera",
                    )
                )
                continue
            alpha_path = frame_dirs[frame] / V1_ALPHA_DIR / f"cam_{serial}.png"
            plan.views.append(
                SourceView(
                    subject=subject,
                    frame=frame,
                    camera=cameras[serial],
                    pattern="full",
                    image=ImageRef(path=str(pngs[frame][serial]), codec="png-srgb"),
                    colour=colour,
                    source=relpath(image_rel),
                    alpha=ImageRef(path=str(alpha_path), codec="png-linear")
                    if alpha_path.is_file()
                    else None,
                )
            )


def plan(src: Path, options: AdapterOptions) -> DatasetPlan:
    """Describe the selected sequence's frames of every participant under ``src`` (see the module docstring).

    Per-participant, per-camera and per-frame problems become Refusals; a folder that is no NeRSemble
    layout raises LayoutError.
    """
    src = Path(src).resolve()
    version = detect(src)
    subjects, sequences, facts = [], {}, {}
    for folder in participant_folders(src):
        subject = check_name(folder.name, "subject", str(folder))
        if not options.keeps_subject(subject):
            continue
        subject_plan = SubjectPlan(subject=subject, split=options.split_of(subject), views=[])
        subjects.append(subject_plan)
        sequence, why = choose_sequence(folder, version, options.sequence)
        if sequence is None:
            subject_plan.refusals.append(
                Refusal(subject, folder.relative_to(src).as_posix() if folder != src else ".", why)
            )
            continue
        sequences[subject] = sequence
        facts[subject] = {}
        planner = _plan_v2 if version == "v2" else _plan_v1
        planner(folder, src, sequence, options, subject_plan, facts[subject])
    found = {
        "layout": version,
        "participants": [s.subject for s in subjects],
        "sequences": sequences,
        "cameras": sorted({v.camera.name for s in subjects for v in s.views}),
        "frames": {s.subject: sorted({v.frame for v in s.views}) for s in subjects},
        "image_size": sorted({tuple(f["image_size"]) for f in facts.values() if "image_size" in f}),
        "downsample_factor": sorted(
            {f["downsample_factor"] for f in facts.values() if "downsample_factor" in f}
        ),
        "colour": "CCM in linear light (color_calibration.json)"
        if version == "v2"
        else "affine in display space (color_correction/*.npy)",
        "alpha_maps": sum(1 for s in subjects for v in s.views if v.alpha is not None),
        "views": sum(len(s.views) for s in subjects),
    }
    return adapter_plan(NAME, KIND, SOURCE_DATASET, LICENCE, version, src, options, subjects, found=found)
