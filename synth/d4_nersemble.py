"""D4: a NeRSemble-v2-like capture (16 cameras, video, colour calibration file).

Layout under ``<out>/nersemble/`` follows the v2 release::

    metadata_sequences.csv                            ID, wears_glasses, one column per sequence ('x' = present)
    {p_id:03d}/calibration/camera_params.json         {"world_2_cam": {serial: 4x4}, "intrinsics": 3x3}
    {p_id:03d}/calibration/color_calibration.json     {serial: 3x3 CCM}
    {p_id:03d}/sequences/EXP-1-head/images/cam_{serial}.mp4
    {p_id:03d}/sequences/BACKGROUND/image_{serial}.jpg   clean background plates

Conventions: ``world_2_cam`` is row-major world->camera with OpenCV axes, metres; ``intrinsics`` is one
matrix shared by the 16 cameras, in pixels of the written video (no distortion). The videos are H.264
(libx264, yuv444p, crf 0: visually lossless, colour survives up to the RGB<->YUV rounding of FFmpeg's
default untagged BT.601 conversion) holding sRGB-encoded recorded colour. The CCM undoes the camera's
colour cast the way the release applies it (``colour.cctf_decoding`` -> ``CCM @ rgb`` -> encoding), so
with 3 Cheung terms ``CCM = inverse(M)``. Eight frontal flashes light the head; a bright plate stands behind it.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import av
import numpy as np
from PIL import Image

from relightanyone.synth.capture import (
    HEAD_AIM_POINT,
    apply_colour_response,
    focal_for_field,
    frontal_flashes,
    intrinsics,
    look_at_w2c,
    native_w2c,
    random_colour_responses,
    random_head_pose,
    random_world_from_canonical,
    report_progress,
    spherical_direction,
    srgb_encode,
    to_uint8,
)
from relightanyone.synth.presets import Preset
from relightanyone.synth.raytrace import PointLights, Scene, SynthCamera, render, textured_quad
from relightanyone.synth.template import HeadTemplate
from relightanyone.synth.truth import DatasetTruth, RenderedRig

NATIVE_DIR = "nersemble"
SERIALS = (
    "222200042",
    "222200044",
    "222200046",
    "222200040",
    "222200036",
    "222200048",
    "220700191",
    "222200041",
    "222200037",
    "222200038",
    "222200047",
    "222200043",
    "222200049",
    "222200039",
    "222200045",
    "221501007",
)
SEQUENCE_NAMES = (
    "BACKGROUND",
    "GLASSES",
    "EXP-1-head",
    "EXP-2-eyes",
    "EXP-3-cheeks+nose",
    "EXP-4-lips",
    "EXP-5-mouth",
    "EXP-6-tongue-1",
    "EXP-7-tongue-2",
    "EXP-8-jaw-1",
    "EXP-9-jaw-2",
    "HAIR",
    "FREE",
    "EMO-1-shout+laugh",
    "EMO-2-surprise+fear",
    "EMO-3-angry+sad",
    "EMO-4-disgust+happy",
)
SEQUENCE = "EXP-1-head"
FPS = 73
EXPOSURE = 0.6
PLATE_DISTANCE_M = 0.45  # background plate behind the head centre
PLATE_ALBEDO = 0.95
DISTANCE_M = 1.0
# (azimuth, elevation) in degrees per camera index; index 8 (serial 222200037) is the frontal centre view.
LAYOUT_DEG = (
    (-60, 18),
    (-40, 18),
    (-20, 18),
    (-60, 0),
    (-40, 0),
    (-20, 0),
    (-60, -14),
    (-20, -14),
    (0, 2),
    (20, 18),
    (40, 18),
    (60, 18),
    (20, 0),
    (40, 0),
    (60, 0),
    (40, -14),
)


def make_cameras(preset: Preset, rng: np.random.Generator) -> list[SynthCamera]:
    """16 cameras with the real serials on a 1 m arc in front of the face, one shared K, no distortion."""
    size = preset.d4
    width, height = size.image_size
    if size.cameras > len(SERIALS):
        raise ValueError(f"the D4 rig has {len(SERIALS)} cameras, preset asks for {size.cameras}")
    K = intrinsics(focal_for_field(height, DISTANCE_M, 0.42), width, height)
    cameras = []
    for index in range(size.cameras):
        azimuth, elevation = LAYOUT_DEG[index]
        direction = spherical_direction(
            np.deg2rad(azimuth + rng.uniform(-2, 2)), np.deg2rad(elevation + rng.uniform(-2, 2))
        )
        eye = HEAD_AIM_POINT + DISTANCE_M * rng.uniform(0.97, 1.03) * direction
        w2c = look_at_w2c(
            eye, HEAD_AIM_POINT + rng.uniform(-0.01, 0.01, 3), roll=float(rng.uniform(-0.02, 0.02))
        )
        cameras.append(SynthCamera(SERIALS[index], K.copy(), w2c, width, height, np.zeros(5)))
    return cameras


def flash_lights(count: int) -> PointLights:
    """``count`` frontal flashes on two rows of a 1.2 m arc, together giving an irradiance of ~pi at the face."""
    return frontal_flashes(count, 70.0, 30.0, -5.0, radius=1.2, mean_cosine=0.6)


def background_plate(rng: np.random.Generator) -> Scene:
    """A bright, slightly mottled 8 m x 8 m plate behind the head, facing +z."""
    half, z = 4.0, -PLATE_DISTANCE_M
    corners = np.array([[-half, half, z], [half, half, z], [half, -half, z], [-half, -half, z]])
    coarse = rng.uniform(-1.0, 1.0, size=(8, 8, 1))
    mottle = np.kron(coarse, np.ones((8, 8, 1)))
    tint = np.array([1.0, 0.98, 0.94])
    albedo = (PLATE_ALBEDO * (1.0 + 0.04 * mottle) * tint).clip(0, 1).astype(np.float32)
    return textured_quad(corners, albedo)


def encode_video(path: Path, frames: list[np.ndarray]) -> None:
    """(H, W, 3) uint8 sRGB frames -> H.264 mp4 (libx264, yuv444p, crf 0, one thread for stable bytes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    height, width = frames[0].shape[:2]
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=FPS)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv444p"
        stream.options = {"crf": "0", "preset": "medium"}
        stream.thread_count = 1
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def jpeg_bytes(image_uint8: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image_uint8).save(buffer, format="JPEG", quality=95)
    return buffer.getvalue()


def subject_names(rng: np.random.Generator, count: int) -> list[str]:
    """Distinct 3-digit participant ids in increasing order (the v2 release numbers people 017..480 or so)."""
    return [f"{int(k):03d}" for k in sorted(rng.choice(np.arange(17, 480), size=count, replace=False))]


def metadata_csv(ids: list[str]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["ID", "wears_glasses", *SEQUENCE_NAMES])
    for pid in ids:
        writer.writerow(
            [int(pid), "", *["x" if s in ("BACKGROUND", SEQUENCE) else "" for s in SEQUENCE_NAMES]]
        )
    return buffer.getvalue()


def generate(
    out_root: Path,
    preset: Preset,
    template: HeadTemplate,
    subjects: list,
    splits: dict[str, str],
    rng: np.random.Generator,
    progress=None,
) -> DatasetTruth:
    """Write the D4 participants (calibration, colour calibration, videos, background plates)."""
    size = preset.d4
    root = Path(out_root) / NATIVE_DIR
    world_from_canonical = random_world_from_canonical(rng, scale=1.0, offset_range=0.3)
    cameras = make_cameras(preset, rng)
    lights = flash_lights(size.lights)
    responses = random_colour_responses(rng, cameras, gain_spread=0.2, crosstalk=0.05)
    plate = background_plate(rng)
    ids = [subject.name for subject in subjects]
    root.mkdir(parents=True, exist_ok=True)
    (root / "metadata_sequences.csv").write_text(metadata_csv(ids))

    camera_params = {
        "world_2_cam": {cam.name: native_w2c(cam.w2c, world_from_canonical).tolist() for cam in cameras},
        "intrinsics": cameras[0].K.tolist(),
        # The size the intrinsics describe (VHAP reads these keys; without them it is the 2200x3208 frame).
        "width": cameras[0].width,
        "height": cameras[0].height,
    }
    colour_calibration = {
        name: np.linalg.inv(response * EXPOSURE).tolist() for name, response in responses.items()
    }

    def recorded_srgb(image: np.ndarray, cam: SynthCamera) -> np.ndarray:
        return to_uint8(srgb_encode(apply_colour_response(image * EXPOSURE, responses[cam.name])))

    plates = {cam.name: recorded_srgb(render(plate, cam, lights).image, cam) for cam in cameras}
    head_poses: dict[tuple[str, int], np.ndarray] = {}
    for subject in subjects:
        folder = root / subject.name
        (folder / "calibration").mkdir(parents=True, exist_ok=True)
        (folder / "calibration" / "camera_params.json").write_text(json.dumps(camera_params, indent=2))
        (folder / "calibration" / "color_calibration.json").write_text(
            json.dumps(colour_calibration, indent=2)
        )
        for cam in cameras:
            plate_path = folder / "sequences" / "BACKGROUND" / f"image_{cam.name}.jpg"
            plate_path.parent.mkdir(parents=True, exist_ok=True)
            plate_path.write_bytes(jpeg_bytes(plates[cam.name]))
        poses = [np.eye(4)] + [random_head_pose(rng, 6.0, 0.008) for _ in range(size.frames - 1)]
        frames: dict[str, list[np.ndarray]] = {cam.name: [] for cam in cameras}
        for frame_index, pose in enumerate(poses):
            head_poses[(subject.name, frame_index)] = pose
            scene = Scene.from_subject(template, subject, head_pose=pose).merge(plate)
            for cam in cameras:
                frames[cam.name].append(
                    recorded_srgb(render(scene, cam, lights, supersampling=preset.supersampling).image, cam)
                )
                report_progress(progress)
        for cam in cameras:
            encode_video(folder / "sequences" / SEQUENCE / "images" / f"cam_{cam.name}.mp4", frames[cam.name])

    extra = {
        "sequence": SEQUENCE,
        "fps": FPS,
        "video": "libx264 yuv444p crf 0, sRGB-encoded recorded colour",
        "background_plate": {"z_m": -PLATE_DISTANCE_M, "albedo": PLATE_ALBEDO},
        "frame_key": "video frame index",
    }
    colour_response = {name: response * EXPOSURE for name, response in responses.items()}
    rig = RenderedRig(world_from_canonical, cameras, lights, colour_response)
    return DatasetTruth.of_rig("d4", "nersemble", NATIVE_DIR, rig, head_poses, splits, extra)


def preview_images(native_root: Path, count: int) -> list[tuple[str, np.ndarray]]:
    """First video frame of the first participant's cameras (the videos already hold sRGB)."""
    participants = sorted(p for p in Path(native_root).glob("[0-9][0-9][0-9]") if p.is_dir())
    if not participants:
        return []
    videos = sorted((participants[0] / "sequences" / SEQUENCE / "images").glob("cam_*.mp4"))
    views = []
    for path in videos[:: max(1, len(videos) // max(count, 1))][:count]:
        with av.open(str(path)) as container:
            frame = next(container.decode(video=0)).to_ndarray(format="rgb24")
        views.append((path.stem, frame))
    return views
