"""D1: a FaceOLAT-like light stage (portrait cameras, a dome of point lights, OLAT takes).

Native layout written under ``out_root / "faceolat"``::

    calibration/cameras/{subject}.xml            Metashape camera XML, one per subject (see .d1_metashape)
    calibration/calibration_mapping.json         subject -> date folder, calibration take / id, capture ids
    color-calibration/colorcalib_exr.mat         text 4x4: 3x3 colour matrix, zero black-level column
    relighting/lights/light_pattern_metadata.json  light positions ("mm" of the calibration world), patterns
    relighting/lights/light_pattern_per_frame.json  the rig's nominal [frame, pattern] schedule
    {subject}/lights/{capture}/light_pattern_per_frame.json   the schedule this take actually used
    {subject}/OutputEXR/Cam01/{capture}/{capture}.{frame:06d}.exr   linear RGB frames (HALF, RLE)

Subjects are "001", "002", ...; a subject's capture (take) id is ``ID2`` + ``0`` + its number, e.g.
``ID20001``. Pattern 0 is "full" (every light on), pattern k >= 1 is ``OLAT_{k-1:03d}`` (light k - 1
alone). Full-on frames come first and then after every 20 frames, and once more at the end, as in the
real schedule; every third subject's take starts with one extra full-on frame, so frame indices differ
between takes. Per-light intensity is proportional to duration / 5555 (Goliath's rule): an OLAT lights
its light for ``n_lights`` units and a full-on frame lights each light for ``n_lights / 20`` units, so a
full-on frame equals 1/20 of the sum of the OLAT frames.

Frames hold ``inverse(M) @ radiance`` where M is the 3x3 block of ``colorcalib_exr.mat``: applying the
file's matrix the FaceOLAT way (``M[:3,:3] @ (rgb - M[:3,3])``) recovers the true radiance.

World frame: the Metashape world (after the chunk transform) is related to canonical head space by
``DatasetTruth.world_from_canonical``, a similarity whose scale is not 1 (the calibration's "metres"
are not true metres). The light positions in the JSON are in thousandths of those world units ("mm").
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from relightanyone.synth.d1_metashape import metashape_document
from relightanyone.synth.envmap import write_exr
from relightanyone.synth.presets import DatasetSize, Preset
from relightanyone.synth.raytrace import PointLights, Scene, SynthCamera, render
from relightanyone.synth.truth import DatasetTruth, RenderedRig

NATIVE_DIR = "faceolat"
D1_RIG_SEED = 331  # the rig is the same in every world: lights come from this seed
DOME_RADIUS = 1.30  # canonical metres
DOME_CENTRE = np.array([0.01, -0.03, 0.02])  # canonical position of the dome centre (the head is near it)
DOME_LOWEST_Y = -0.8  # no lights below this direction height (the floor and the cameras' side)
OLAT_INTENSITY = 2.5  # linear RGB radiant intensity of one light during an OLAT frame
DURATION_UNIT = 5555.0  # Goliath: intensity = duration / 5555
FULL_ON_PERIOD = 20  # a full-on frame every ~20 frames
FRAME_COMPRESSION = "rle"  # frames are many and small: RLE writes twice as fast as ZIP
CAMERA_DISTANCE = (1.0, 1.15)  # canonical metres from the head
VERTICAL_FIELD = 0.40  # metres of head covered by the image height at the camera distance
HEAD_AIM = np.array([0.0, -0.025, 0.01])  # cameras look here
# FaceOLAT's own colorcalib_exr.mat 3x3 block; each synthetic world perturbs it slightly.
REFERENCE_COLOUR_MATRIX = np.array(
    [
        [1.38336957, -0.0137942024, 0.0225721952],
        [0.000634239288, 1.09661555, 0.108807974],
        [-0.0480271429, 0.128822848, 1.75287747],
    ]
)


def _rng(rng_or_seed) -> np.random.Generator:
    if isinstance(rng_or_seed, np.random.Generator):
        return rng_or_seed
    return np.random.default_rng(int(rng_or_seed))


def dome_directions(count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) unit directions spread evenly (Fibonacci spiral) over the dome cap y >= DOME_LOWEST_Y."""
    i = np.arange(count) + 0.5
    y = 1.0 - (1.0 - DOME_LOWEST_Y) * i / count
    azimuth = np.pi * (3.0 - np.sqrt(5.0)) * i + rng.uniform(0, 2 * np.pi)
    ring = np.sqrt(1.0 - y**2)
    dirs = np.stack([ring * np.sin(azimuth), y, ring * np.cos(azimuth)], axis=1)
    dirs += rng.normal(0, 0.15 / np.sqrt(max(count, 1)), size=dirs.shape)  # mounting imprecision
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def d1_rig_lights(preset: Preset, rng_or_seed=D1_RIG_SEED) -> PointLights:
    """The D1 dome of ``preset.d1.lights`` point lights in canonical space, at their OLAT intensities.

    :func:`generate` uses ``d1_rig_lights(preset, D1_RIG_SEED)``; pass the same seed to reuse its rig.
    """
    rng = _rng(rng_or_seed)
    count = preset.d1.lights
    if count < 1:
        raise ValueError(f"preset {preset.name!r}: d1 needs at least one light")
    positions = DOME_CENTRE + DOME_RADIUS * dome_directions(count, rng)
    tint = rng.uniform(0.97, 1.03, size=(count, 3))  # LEDs differ a little in colour
    return PointLights(positions, OLAT_INTENSITY * tint)


def light_scan_order(positions: np.ndarray) -> np.ndarray:
    """(L,) light indices in the order a dome controller would scan them: bands top-down, serpentine."""
    rel = positions - DOME_CENTRE
    dirs = rel / np.linalg.norm(rel, axis=1, keepdims=True)
    bands = max(1, int(round(np.sqrt(len(positions)) / 2)))
    band = np.minimum(((1.0 - dirs[:, 1]) / (1.0 - DOME_LOWEST_Y + 1e-9) * bands).astype(int), bands - 1)
    azimuth = np.arctan2(dirs[:, 0], dirs[:, 2])
    key_azimuth = np.where(band % 2 == 0, azimuth, -azimuth)
    return np.lexsort((key_azimuth, band))


def light_schedule(scan_order: np.ndarray, extra_leading_full: bool = False) -> list[list[int]]:
    """``[[frame, pattern], ...]``: full-on (0) at the start, every FULL_ON_PERIOD frames and at the end.

    OLAT patterns (light index + 1) follow ``scan_order``. With ``extra_leading_full`` the take has
    one more full-on frame at frame 0 and everything else moves one frame later.
    """
    shift = 1 if extra_leading_full else 0
    patterns = [0] * (1 + shift)
    for light in scan_order:
        # Real takes: full-on at frames 0, 20, 41, 62, ... (every 21 frames after the first 20).
        position = len(patterns) - shift
        if position >= FULL_ON_PERIOD and (position - FULL_ON_PERIOD) % (FULL_ON_PERIOD + 1) == 0:
            patterns.append(0)
        patterns.append(int(light) + 1)
    patterns.append(0)
    return [[frame, pattern] for frame, pattern in enumerate(patterns)]


def light_pattern_metadata(positions_mm: np.ndarray) -> dict:
    """The Goliath/FaceOLAT ``light_pattern_metadata.json`` content for lights at ``positions_mm`` (L, 3)."""
    n = len(positions_mm)
    full = [[i, round(n / FULL_ON_PERIOD, 4)] for i in range(n)]
    patterns = [{"name": "full", "light_index_durations": full}]
    patterns += [{"name": f"OLAT_{i:03d}", "light_index_durations": [[i, n]]} for i in range(n)]
    return {
        "light_positions": np.asarray(positions_mm, dtype=np.float64).tolist(),
        "light_patterns": patterns,
    }


def colour_matrix_text(matrix: np.ndarray) -> str:
    """FaceOLAT's text 4x4: 3x3 block, zero 4th column, last row 0 0 0 1, trailing spaces, no final newline."""
    rows = np.zeros((4, 4))
    rows[:3, :3] = matrix
    rows[3, 3] = 1.0
    return "\n".join(" ".join(format(v, ".9g") for v in row) + " " for row in rows)


def rig_cameras(size: DatasetSize, rng: np.random.Generator) -> list[SynthCamera]:
    """``size.cameras`` portrait cameras on three height tiers around the front of the head."""
    width, height = size.image_size
    cams = []
    n = size.cameras
    for index in range(n):
        azimuth = np.radians(-100 + 200 * (index + 0.5) / n + rng.normal(0, 2))
        elevation = np.radians((-12.0, 8.0, 28.0)[index % 3] + rng.normal(0, 3))
        distance = rng.uniform(*CAMERA_DISTANCE)
        centre = HEAD_AIM + distance * np.array(
            [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        )
        forward = HEAD_AIM + rng.normal(0, 0.008, 3) - centre
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        roll = np.radians(rng.normal(0, 1.5))
        right, down = np.cos(roll) * right + np.sin(roll) * down, -np.sin(roll) * right + np.cos(roll) * down
        w2c = np.eye(4)
        w2c[:3, :3] = np.stack([right, down, forward])
        w2c[:3, 3] = -w2c[:3, :3] @ centre
        f = height * distance / VERTICAL_FIELD * rng.uniform(0.95, 1.05)
        b1 = rng.normal(0, 3e-4) * f
        cx = width / 2.0 - 0.5 + rng.normal(0, 0.008) * width
        cy = height / 2.0 - 0.5 + rng.normal(0, 0.008) * height
        K = np.array([[f + b1, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        dist = np.array(
            [
                rng.uniform(-0.3, 0.3),
                rng.uniform(-2.0, 2.0),
                rng.normal(0, 3e-4),
                rng.normal(0, 3e-4),
                rng.uniform(-10, 10),
            ]
        )
        cams.append(SynthCamera(f"Cam{index + 1:02d}", K, w2c, width, height, dist))
    return cams


def world_from_canonical_transform(rng: np.random.Generator) -> np.ndarray:
    """(4, 4) similarity: the calibration world of the stage <- canonical metres.

    The world is y-up like the rig (a yaw about +y), the dome centre sits near FaceOLAT's
    (606, 1551, 536) mm, and its unit is not a true metre (scale 1.15 to 1.45).
    """
    scale = rng.uniform(1.15, 1.45)
    rotation = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi)).as_matrix()
    m = np.eye(4)
    m[:3, :3] = scale * rotation
    m[:3, 3] = np.array([0.606, 1.551, 0.536]) - m[:3, :3] @ DOME_CENTRE
    return m


def head_pose(rng: np.random.Generator) -> np.ndarray:
    """(4, 4) a subject's seating in the stage: a few degrees of rotation, about a centimetre of offset."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.04, 3)).as_matrix()
    pose[:3, 3] = rng.normal(0, 0.008, 3)
    return pose


def _advance(progress, n: int = 1) -> None:
    if progress is None:
        return
    if hasattr(progress, "update"):
        progress.update(n)
    else:
        progress(n)


def _write_json(path: Path, data, indent: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=indent))


def capture_id(subject: str) -> str:
    """FaceOLAT capture id of a subject's (only) take: ``ID2`` + ``0`` + the three-digit subject number."""
    return f"ID20{subject}"


def generate(
    out_root: Path,
    preset: Preset,
    template,
    subjects: list,
    splits: dict[str, str],
    rng: np.random.Generator,
    progress=None,
) -> DatasetTruth:
    """Write the D1 dataset under ``out_root / "faceolat"`` and return its truth.

    Subjects must be named "001", "002", ... (the FaceOLAT subject folders). ``progress`` is advanced
    once per rendered (subject, camera).
    """
    size = preset.d1
    root = Path(out_root) / NATIVE_DIR
    for subject in subjects:
        if len(subject.name) != 3 or not subject.name.isdigit():
            raise ValueError(f"D1 subject names must be three digits like '001', got {subject.name!r}")
    lights = d1_rig_lights(preset, D1_RIG_SEED)
    cameras = rig_cameras(size, rng)
    world_from_canonical = world_from_canonical_transform(rng)
    colour_matrix = REFERENCE_COLOUR_MATRIX * rng.uniform(0.98, 1.02, size=(3, 3))
    response = np.linalg.inv(colour_matrix)  # recorded = response @ true
    subject_seed = int(rng.integers(2**31))

    positions_world = lights.positions @ world_from_canonical[:3, :3].T + world_from_canonical[:3, 3]
    _write_json(
        root / "relighting/lights/light_pattern_metadata.json",
        light_pattern_metadata(1000.0 * positions_world),
        4,
    )
    order = light_scan_order(lights.positions)
    _write_json(root / "relighting/lights/light_pattern_per_frame.json", light_schedule(order), 4)
    (root / "color-calibration").mkdir(parents=True, exist_ok=True)
    (root / "color-calibration/colorcalib_exr.mat").write_text(colour_matrix_text(colour_matrix))

    n_lights = len(lights)
    full_scale = (n_lights / FULL_ON_PERIOD) / n_lights  # full-on duration per light / OLAT duration
    head_poses, full_on_frames, chunk_transforms, mapping = {}, {}, {}, []
    for index, subject in enumerate(subjects):
        srng = np.random.default_rng([subject_seed, index])
        capture = capture_id(subject.name)
        pose = head_pose(srng)
        chunk_scale = float(np.exp(srng.uniform(np.log(0.5), np.log(2.0))))
        chunk_rotation = Rotation.random(random_state=srng).as_matrix()
        chunk_translation = srng.normal(0, 2.0, 3)
        xml = metashape_document(
            cameras, world_from_canonical, chunk_scale, chunk_rotation, chunk_translation, pose[:3, 3], srng
        )
        (root / "calibration/cameras").mkdir(parents=True, exist_ok=True)
        (root / f"calibration/cameras/{subject.name}.xml").write_text(xml)
        chunk = np.eye(4)
        chunk[:3, :3] = chunk_scale * chunk_rotation
        chunk[:3, 3] = chunk_translation
        chunk_transforms[subject.name] = chunk.tolist()
        mapping.append(
            {
                "subject_name": subject.name,
                "date_folder": f"2024_09_{19 + index // 6:02d}",
                "calibration_take_number": f"C{11 + 6 * index:03d}",
                "calibration_id": f"CB{index + 2:04d}",
                "unique_ids": [capture],
            }
        )

        schedule = light_schedule(order, extra_leading_full=(index % 3 == 1))
        _write_json(root / f"{subject.name}/lights/{capture}/light_pattern_per_frame.json", schedule, 4)
        full_on_frames[subject.name] = [frame for frame, pattern in schedule if pattern == 0]
        for frame, _ in schedule:
            head_poses[(subject.name, frame)] = pose

        scene = Scene.from_subject(template, subject, head_pose=pose)
        for cam in cameras:
            olat = render(scene, cam, lights, per_light=True, supersampling=preset.supersampling).image
            recorded = olat @ response.T.astype(np.float32)  # (L, H, W, 3)
            full = recorded.sum(axis=0, dtype=np.float64) * full_scale
            folder = root / subject.name / "OutputEXR" / cam.name / capture
            first_full = None
            for frame, pattern in schedule:
                path = folder / f"{capture}.{frame:06d}.exr"
                if pattern == 0:
                    if first_full is None:  # every full-on frame of a still take is the same image
                        write_exr(path, full, half=True, compression=FRAME_COMPRESSION)
                        first_full = path
                    else:
                        shutil.copyfile(first_full, path)
                else:
                    write_exr(path, recorded[pattern - 1], half=True, compression=FRAME_COMPRESSION)
            _advance(progress, 1)

    _write_json(
        root / "calibration/calibration_mapping.json",
        {
            "summary": {"total_subjects": len(subjects), "unique_calibrations": len(subjects)},
            "calibrations": mapping,
        },
        2,
    )
    extra = {
        "full_on_frames": full_on_frames,
        "capture_ids": {s.name: capture_id(s.name) for s in subjects},
        "full_on_scale": full_scale,
        "olat_duration": n_lights,
        # A light's intensity for a pattern is this * duration / DURATION_UNIT (canonical units).
        "intensity_at_full_duration": (lights.intensities * DURATION_UNIT / n_lights).tolist(),
        "full_duration_per_light": round(n_lights / FULL_ON_PERIOD, 4),
        "light_file_units_per_world_unit": 1000.0,
        "chunk_transforms": chunk_transforms,
        "colour_matrix_file": colour_matrix.tolist(),
        "rig_seed": D1_RIG_SEED,
        "light_scan_order": order.tolist(),
        "frames": "EXR HALF, recorded = colour_response @ radiance; head still during a take",
    }
    rig = RenderedRig(world_from_canonical, cameras, lights, {c.name: response for c in cameras})
    return DatasetTruth.of_rig("d1", "faceolat", NATIVE_DIR, rig, head_poses, splits, extra)
