"""D2: an Ava-256-like flat-lit capture (Meta Codec Avatar Studio layout).

Layout written under ``<out>/ava256/`` (the Ava-256 release's), one capture folder per subject::

    {mcd}--{mct}--{sid}/decoder/
        camera_calibration.json        {"KRT": [{cameraId, projectionModel, distortionModel, K, distortion, T}]}
        frame_list.csv                 header "seg_id,frame_id"; frame 0 of every capture is EXP_neutral_peak
        head_pose/head_pose.zip        {frame:06d}.txt: 3x4 head (mm) -> world (mm), np.loadtxt-readable
        image/cam{id}.zip              uncompressed; members cam{id}/{frame:06d}.avif

Conventions, as in the real release: ``K`` and ``T`` are stored TRANSPOSED; ``T`` is world->camera in
millimetres; ``K`` is in pixels of the real rig's full 2668x4096 sensor, of which the written images are a
downscale (``SENSOR`` / image size per axis, rounded like the release's ``4096 // ds, 2668 // ds``; the
sensor principal point follows the pixel-centre rule ``c_sensor = (c + 0.5) * s - 0.5``);
``distortion`` holds OpenCV k1 k2 p1 p2 (k3 = 0). AVIF files hold the camera's recorded LINEAR RGB as
8-bit codes (no transfer curve, as the real AVIFs per ava-256#32), quality 63, after a per-camera 3x3
colour cast; no colour calibration file is written. Lighting is even: point lights spread over the whole
sphere. One image of one camera is missing from its zip (a dropped frame, listed in truth.extra).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from PIL import Image

from relightanyone.synth.capture import (
    HEAD_AIM_POINT,
    apply_colour_response,
    fibonacci_sphere,
    focal_for_field,
    intrinsics,
    look_at_w2c,
    native_head_pose,
    native_w2c,
    random_colour_responses,
    random_head_pose,
    random_world_from_canonical,
    report_progress,
    spherical_direction,
    srgb_encode,
    to_uint8,
    write_zip,
)
from relightanyone.synth.presets import Preset
from relightanyone.synth.raytrace import PointLights, Scene, SynthCamera, render
from relightanyone.synth.template import HeadTemplate
from relightanyone.synth.truth import DatasetTruth, RenderedRig

NATIVE_DIR = "ava256"
SENSOR = (2668, 4096)  # (width, height) of the sensor the calibration describes, as the real rig's
AVIF_QUALITY = 63  # the 4TB release's AVIF quality (ava-256#9)
NEUTRAL_SEGMENT = "EXP_neutral_peak"
OTHER_SEGMENTS = ("EXP_free_face", "EXP_jaw_open", "EXP_smile")
FRAME_STEP = 4  # native frame ids advance by 4 between kept frames (30 fps capture, 7.5 fps release)
LIGHT_RADIUS = 1.6  # m, lights of the even-lighting sphere
EXPOSURE = 0.8  # recorded value of a white Lambertian surface under the full even light, before the cast


def subject_names(rng: np.random.Generator, count: int) -> list[str]:
    """``count`` distinct Ava-256-style subject ids (three letters, three digits, e.g. AAN112)."""
    names: list[str] = []
    while len(names) < count:
        letters = "".join(chr(ord("A") + int(k)) for k in rng.integers(0, 26, size=3))
        name = f"{letters}{int(rng.integers(100, 1000))}"
        if name not in names:
            names.append(name)
    return names


def capture_folder(rng: np.random.Generator, sid: str) -> str:
    """``{mcd}--{mct}--{sid}`` with a capture date YYYYMMDD and time HHMM (download.py's folder name)."""
    mcd = f"2023{int(rng.integers(1, 13)):02d}{int(rng.integers(1, 29)):02d}"
    mct = f"{int(rng.integers(7, 19)):02d}{int(rng.integers(0, 60)):02d}"
    return f"{mcd}--{mct}--{sid}"


def make_cameras(preset: Preset, rng: np.random.Generator) -> list[SynthCamera]:
    """Portrait cameras on the front of a dome (azimuth -100..100 deg, three elevation rows), canonical space."""
    size = preset.d2
    width, height = size.image_size
    count = size.cameras
    azimuths = np.deg2rad(np.linspace(-100.0, 100.0, count) + rng.uniform(-4.0, 4.0, count))
    rows = np.array([-12.0, 8.0, 28.0])
    elevations = np.deg2rad(rows[np.arange(count) % 3] + rng.uniform(-4.0, 4.0, count))
    distances = rng.uniform(1.1, 1.3, count)
    ids = sorted(int(k) for k in rng.choice(np.arange(400000, 401600), size=count, replace=False))
    cameras = []
    for index in range(count):
        eye = HEAD_AIM_POINT + distances[index] * spherical_direction(azimuths[index], elevations[index])
        target = HEAD_AIM_POINT + rng.uniform(-0.015, 0.015, 3)
        w2c = look_at_w2c(eye, target, roll=float(rng.uniform(-0.04, 0.04)))
        focal = focal_for_field(height, distances[index], 0.40) * rng.uniform(0.97, 1.03)
        K = intrinsics(focal, width, height, rng.uniform(-2.0, 2.0, 2), aspect=rng.uniform(0.998, 1.002))
        dist = np.array(
            [
                rng.uniform(-0.08, 0.02),
                rng.uniform(-0.02, 0.05),
                rng.uniform(-0.002, 0.002),
                rng.uniform(-0.002, 0.002),
                0.0,
            ]
        )
        cameras.append(SynthCamera(f"{ids[index]}", K, w2c, width, height, dist))
    return cameras


def even_lights(count: int) -> PointLights:
    """``count`` equal white point lights over the whole sphere (the "even 360 degree" studio light).

    Intensity is set so that a surface facing any direction receives an irradiance of about pi
    (a white Lambertian surface then has radiance about 1) before shadowing.
    """
    positions = HEAD_AIM_POINT + LIGHT_RADIUS * fibonacci_sphere(count)
    per_light = 4.0 * np.pi * LIGHT_RADIUS**2 / count
    return PointLights(positions=positions, intensities=np.full((count, 3), per_light))


def sensor_scale(image_size: tuple[int, int]) -> tuple[float, float]:
    """Per-axis ``SENSOR / image`` of written images of ``image_size`` (width, height); ValueError when the
    image is no downscale of the sensor (the two axes round to different factors)."""
    width, height = image_size
    sx, sy = SENSOR[0] / width, SENSOR[1] / height
    factor = sy if height >= width else sx
    if abs(SENSOR[0] / factor - width) >= 1.0 or abs(SENSOR[1] / factor - height) >= 1.0:
        raise ValueError(
            f"D2 images of {width}x{height} are no downscale of the {SENSOR[0]}x{SENSOR[1]} Ava-256 sensor; "
            f"choose a size of its aspect ratio (e.g. {round(SENSOR[0] / factor)}x{height})"
        )
    return sx, sy


def sensor_intrinsics(K_image: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """K of the full sensor that written images of ``image_size`` (width, height) downscale (pixel-centre rule)."""
    K = np.array(K_image, dtype=np.float64)
    for axis, s in enumerate(sensor_scale(image_size)):
        K[axis, axis] *= s
        K[axis, 2] = (K[axis, 2] + 0.5) * s - 0.5
    return K


def krt_entry(camera: SynthCamera, world_from_canonical: np.ndarray) -> dict:
    """One ``KRT`` element with the real file's keys and its transposed storage (K, T)."""
    w2c_mm = native_w2c(camera.w2c, world_from_canonical)
    return {
        "cameraId": camera.name,
        "projectionModel": "Pinhole",
        "distortionModel": "RadialAndTangential",
        "K": sensor_intrinsics(camera.K, (camera.width, camera.height)).T.tolist(),
        "distortion": [float(v) for v in camera.dist[:4]],
        "T": w2c_mm.T.tolist(),
    }


def encode_avif(recorded_linear: np.ndarray) -> bytes:
    """(H, W, 3) recorded linear RGB -> AVIF bytes holding 8-bit linear codes."""
    buffer = io.BytesIO()
    Image.fromarray(to_uint8(recorded_linear)).save(buffer, format="AVIF", quality=AVIF_QUALITY, speed=8)
    return buffer.getvalue()


def frame_list_csv(frame_ids: list[int]) -> str:
    """``seg_id,frame_id`` rows: the first frame is the neutral peak, later frames other segments."""
    rows = ["seg_id,frame_id"]
    for index, frame_id in enumerate(frame_ids):
        segment = NEUTRAL_SEGMENT if index == 0 else OTHER_SEGMENTS[(index - 1) % len(OTHER_SEGMENTS)]
        rows.append(f"{segment},{frame_id}")
    return "\n".join(rows) + "\n"


def head_pose_text(pose_3x4: np.ndarray) -> bytes:
    """3x4 matrix as np.loadtxt-readable text."""
    return "".join(" ".join(f"{v:.9f}" for v in row) + "\n" for row in pose_3x4).encode()


def generate(
    out_root: Path,
    preset: Preset,
    template: HeadTemplate,
    subjects: list,
    splits: dict[str, str],
    rng: np.random.Generator,
    progress=None,
) -> DatasetTruth:
    """Write the D2 captures of ``subjects`` under ``out_root/ava256`` and return their truth."""
    size = preset.d2
    root = Path(out_root) / NATIVE_DIR
    world_from_canonical = random_world_from_canonical(rng, scale=1000.0, offset_range=800.0)
    cameras = make_cameras(preset, rng)
    lights = even_lights(size.lights)
    responses = random_colour_responses(rng, cameras, gain_spread=0.25, crosstalk=0.06)
    dropped = {
        "subject": subjects[0].name,
        "camera": cameras[int(rng.integers(0, len(cameras)))].name,
        "frame_index": size.frames - 1,
    }
    calibration = json.dumps(
        {"KRT": [krt_entry(cam, world_from_canonical) for cam in cameras]}, indent=4
    ).encode()

    head_poses: dict[tuple[str, int], np.ndarray] = {}
    captures: dict[str, dict] = {}
    for subject in subjects:
        folder = capture_folder(rng, subject.name)
        first = int(rng.integers(1000, 40000))
        # Kept frames of different segments lie far apart in the capture.
        frame_ids = [first + FRAME_STEP * 37 * k for k in range(size.frames)]
        poses = [np.eye(4)] + [random_head_pose(rng, 8.0, 0.01) for _ in range(size.frames - 1)]
        decoder = root / folder / "decoder"
        decoder.mkdir(parents=True, exist_ok=True)
        (decoder / "camera_calibration.json").write_bytes(calibration)
        (decoder / "frame_list.csv").write_text(frame_list_csv(frame_ids))
        write_zip(
            decoder / "head_pose" / "head_pose.zip",
            [
                (f"{fid:06d}.txt", head_pose_text(native_head_pose(pose, world_from_canonical)[:3]))
                for fid, pose in zip(frame_ids, poses, strict=True)
            ],
        )
        members: dict[str, list[tuple[str, bytes]]] = {cam.name: [] for cam in cameras}
        for frame_index, (frame_id, pose) in enumerate(zip(frame_ids, poses, strict=True)):
            head_poses[(subject.name, frame_id)] = pose
            scene = Scene.from_subject(template, subject, head_pose=pose)
            for cam in cameras:
                result = render(scene, cam, lights, supersampling=preset.supersampling)
                recorded = apply_colour_response(result.image * EXPOSURE, responses[cam.name])
                skip = (
                    subject.name == dropped["subject"]
                    and cam.name == dropped["camera"]
                    and frame_index == dropped["frame_index"]
                )
                if not skip:
                    members[cam.name].append((f"cam{cam.name}/{frame_id:06d}.avif", encode_avif(recorded)))
                report_progress(progress)
        for cam in cameras:
            write_zip(decoder / "image" / f"cam{cam.name}.zip", members[cam.name])
        captures[subject.name] = {"folder": folder, "frame_ids": frame_ids}
        if subject.name == dropped["subject"]:
            dropped["frame_id"] = frame_ids[dropped["frame_index"]]

    extra = {
        "captures": captures,
        "dropped_images": [dropped],
        "sensor": list(SENSOR),
        "sensor_scale": list(sensor_scale(size.image_size)),
        "image_encoding": "8-bit linear recorded RGB in AVIF (no transfer curve)",
        "head_pose_convention": "native head space = canonical space in mm; file = head(mm) -> world(mm)",
        "frame_key": "native frame id",
    }
    colour_response = {name: response * EXPOSURE for name, response in responses.items()}
    rig = RenderedRig(world_from_canonical, cameras, lights, colour_response)
    return DatasetTruth.of_rig("d2", "ava256", NATIVE_DIR, rig, head_poses, splits, extra)


def preview_images(native_root: Path, count: int) -> list[tuple[str, np.ndarray]]:
    """Up to ``count`` (label, sRGB uint8 (H, W, 3)) views of the first capture, decoded from its zips."""
    import zipfile

    captures = sorted(p for p in Path(native_root).glob("*/decoder") if p.is_dir())
    if not captures:
        return []
    views = []
    for archive_path in sorted((captures[0] / "image").glob("cam*.zip"))[:count]:
        with zipfile.ZipFile(archive_path) as archive:
            names = sorted(archive.namelist())
            if not names:
                continue
            codes = np.asarray(Image.open(io.BytesIO(archive.read(names[0]))).convert("RGB"))
        # The AVIFs hold linear codes: encode them for display.
        views.append((f"{archive_path.stem}", to_uint8(srgb_encode(codes / 255.0))))
    return views
