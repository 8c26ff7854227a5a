"""Capture-rig helpers shared by the flat-lit dataset generators (D2, D3, D4).

Camera placement (look-at rigs on spheres and arcs), point-light rigs, per-camera colour responses,
similarity transforms between canonical head space and a dataset's native world, and byte-stable
container writers (zip members with a fixed date). Everything is seeded by the caller's
``np.random.Generator`` so that the same seed gives the same bytes.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from relightanyone.synth.raytrace import PointLights

# Zip members carry this date so that archives do not depend on when they were written.
FIXED_ZIP_DATE = (1980, 1, 1, 0, 0, 0)

# Canonical point the rigs aim at: a little in front of the head centre, at eye height.
HEAD_AIM_POINT = np.array([0.0, 0.0, 0.03])


def look_at_w2c(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0), roll: float = 0.0) -> np.ndarray:
    """World-to-camera (OpenCV: x right, y down, z forward) of a camera at ``eye`` looking at ``target``.

    eye, target: (3,) in the same frame; up: the frame's up direction; roll: radians about the optical axis.
    Returns (4, 4) float64.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking straight along up: any right vector will do
        right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    if roll:
        c, s = np.cos(roll), np.sin(roll)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ rotation
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ eye
    return w2c


def spherical_direction(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """Unit directions (N, 3) in canonical space; azimuth 0 is +z (the face), positive towards +x, elevation up."""
    azimuth, elevation = np.asarray(azimuth, dtype=np.float64), np.asarray(elevation, dtype=np.float64)
    return np.stack(
        [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)], axis=-1
    )


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly evenly spread unit directions (count, 3) covering the whole sphere."""
    index = np.arange(count, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * index / count
    radius = np.sqrt(np.clip(1.0 - y * y, 0.0, None))
    phi = index * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([radius * np.sin(phi), y, radius * np.cos(phi)], axis=-1)


def focal_for_field(image_height: int, distance: float, field_height: float) -> float:
    """Focal length in pixels so that ``field_height`` metres at ``distance`` fill ``image_height`` pixels."""
    return float(image_height) * distance / field_height


def intrinsics(focal: float, width: int, height: int, principal_offset=(0.0, 0.0), aspect: float = 1.0):
    """(3, 3) K with the principal point at the image centre (pixel centres at integers) plus an offset."""
    return np.array(
        [
            [focal, 0.0, (width - 1) / 2.0 + principal_offset[0]],
            [0.0, focal * aspect, (height - 1) / 2.0 + principal_offset[1]],
            [0.0, 0.0, 1.0],
        ]
    )


def random_colour_response(rng: np.random.Generator, gain_spread: float, crosstalk: float) -> np.ndarray:
    """A camera's 3x3 colour response M (recorded_linear = M @ true_linear): channel gains around 1
    (a white-balance cast) plus small non-negative cross-channel terms (overlapping filter spectra, so
    a sensor never records negative light; the correcting matrix then has the usual negative off-diagonals)."""
    gains = np.exp(rng.uniform(-gain_spread, gain_spread, size=3))
    mixing = np.eye(3) + rng.uniform(0.0, crosstalk, size=(3, 3)) * (1.0 - np.eye(3))
    response = np.diag(gains) @ mixing
    if np.linalg.cond(response) > 10:  # keep the cast correctable by a well-conditioned 3x3
        raise ValueError("colour response is ill-conditioned; lower the crosstalk")
    return response


def random_colour_responses(
    rng: np.random.Generator, cameras: list, gain_spread: float, crosstalk: float
) -> dict[str, np.ndarray]:
    """Camera name -> its own :func:`random_colour_response`, drawn in camera order."""
    return {cam.name: random_colour_response(rng, gain_spread, crosstalk) for cam in cameras}


def frontal_flashes(
    count: int, half_span_deg: float, upper_deg: float, lower_deg: float, radius: float, mean_cosine: float
) -> PointLights:
    """``count`` flashes on an arc of ``radius`` metres around the head, azimuths evenly over
    ±``half_span_deg``, alternating between elevations ``upper_deg`` and ``lower_deg``. Together they give
    an irradiance of ~pi at the face, which sees them at a mean cosine of ``mean_cosine``."""
    azimuths = np.deg2rad(np.linspace(-half_span_deg, half_span_deg, count))
    elevations = np.deg2rad(np.where(np.arange(count) % 2 == 0, upper_deg, lower_deg))
    positions = HEAD_AIM_POINT + radius * spherical_direction(azimuths, elevations)
    per_light = np.pi * radius**2 / (mean_cosine * count)
    return PointLights(positions=positions, intensities=np.full((count, 3), per_light))


def similarity_matrix(rotation: np.ndarray, translation: np.ndarray, scale: float) -> np.ndarray:
    """(4, 4) x -> scale * rotation @ x + translation."""
    matrix = np.eye(4)
    matrix[:3, :3] = scale * np.asarray(rotation, dtype=np.float64)
    matrix[:3, 3] = translation
    return matrix


def random_world_from_canonical(rng: np.random.Generator, scale: float, offset_range: float) -> np.ndarray:
    """A dataset's native world frame: a random rotation, a translation within ``offset_range`` (native units)
    and a unit conversion ``scale`` (1000 for millimetres). Returns (4, 4) native <- canonical metres."""
    rotation = Rotation.from_rotvec(rng.normal(size=3) * 0.6).as_matrix()
    translation = rng.uniform(-offset_range, offset_range, size=3)
    return similarity_matrix(rotation, translation, scale)


def native_w2c(w2c_canonical: np.ndarray, world_from_canonical: np.ndarray) -> np.ndarray:
    """Camera extrinsic in a native world whose length unit is ``scale`` times the metre.

    The camera frame is scaled with the world (camera coordinates in native units), so projection is unchanged.
    w2c_canonical, world_from_canonical: (4, 4). Returns the rigid (4, 4) native world -> camera (native units).
    """
    scale = np.cbrt(np.linalg.det(world_from_canonical[:3, :3]))
    scaling = np.diag([scale, scale, scale, 1.0])
    return scaling @ w2c_canonical @ np.linalg.inv(world_from_canonical)


def native_head_pose(head_pose: np.ndarray, world_from_canonical: np.ndarray) -> np.ndarray:
    """Rigid head (native units) -> native world of a canonical head motion ``head_pose`` (4, 4).

    The native head space is canonical space expressed in native units, so the result is rigid.
    """
    scale = np.cbrt(np.linalg.det(world_from_canonical[:3, :3]))
    return world_from_canonical @ head_pose @ np.diag([1.0 / scale, 1.0 / scale, 1.0 / scale, 1.0])


def random_head_pose(rng: np.random.Generator, max_angle_deg: float, max_shift_m: float) -> np.ndarray:
    """Small rigid head motion in canonical space (4, 4): a rotation about the head centre plus a shift."""
    rotvec = rng.uniform(-1.0, 1.0, size=3) * np.deg2rad(max_angle_deg) * np.array([0.6, 1.0, 0.4])
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = rng.uniform(-max_shift_m, max_shift_m, size=3)
    return pose


def write_zip(path: Path, members: list[tuple[str, bytes]]) -> None:
    """Uncompressed zip (random access per member, as the Ava-256 archives) with fixed member dates."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for name, data in members:
            info = zipfile.ZipInfo(name, date_time=FIXED_ZIP_DATE)
            info.external_attr = 0o644 << 16
            archive.writestr(info, data)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer (clipped to [0, 1]); any shape."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1.0 / 2.4) - 0.055)


def to_uint8(values01: np.ndarray) -> np.ndarray:
    """Round [0, 1] floats to 8-bit codes."""
    return np.clip(np.round(np.asarray(values01) * 255.0), 0, 255).astype(np.uint8)


def apply_colour_response(image: np.ndarray, response: np.ndarray) -> np.ndarray:
    """(..., 3) true linear -> recorded linear ``response @ rgb`` per pixel."""
    return np.einsum("ij,...j->...i", response, image)


def report_progress(progress, amount: int = 1) -> None:
    """Advance a tqdm bar or call a ``progress(n)`` callable; ``None`` does nothing."""
    if progress is None:
        return
    update: Callable[[int], object] | None = getattr(progress, "update", None)
    if update is not None:
        update(amount)
    else:
        progress(amount)
