"""What a single-image fit is given: nothing another view or the capture rig would have supplied.

A fit from one photograph has no multi-view tracking, no dataset mask and no calibration. Table 2's
single-image fit therefore replaces all three with what one image yields:

* **Mesh**: the world's tracked mesh degraded to a monocular tracker's typical error. Monocular FLAME
  regressors reach about 1.1-1.6 mm mean scan-to-mesh error on the NoW benchmark, measured *after* a
  rigid alignment to the scan, so the rigid part of their error comes on top: a few degrees of head
  rotation and, since one image fixes size only together with depth, an error along the camera's optical
  axis. The degradation is a smooth random displacement field of ``SHAPE_RMS_M`` (1.5 mm) RMS per vertex,
  a rotation about the head centre by ``ROTATION_SIGMA_DEG`` (2°) and a shift along the optical axis
  of ``DEPTH_SIGMA_M`` (1 cm) standard deviation, drawn per subject from the evaluation seed.
* **Mask**: the foreground of the image alone (a matte): pixels brighter than ``FOREGROUND_FRACTION`` of
  the image's 99th-percentile luminance, the largest connected region with its holes filled. Unlike the
  datasets' masks it is not cut below the neck line (that cut comes from multi-view tracking).
* **Focal length**: a generic value, the field of view ``GENERIC_FOV_DEG`` (15°) across the image width,
  with the camera moved along its optical axis so that the head centre keeps its depth-scaled size (what a
  monocular tracker does when it fixes the focal length and estimates the distance). The principal point
  stays at the crop's.
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import torch

from relightanyone.model.fit.views import FitViews

SHAPE_RMS_M = 0.0015
ROTATION_SIGMA_DEG = 2.0
DEPTH_SIGMA_M = 0.01
SHAPE_WAVES = 6  # low-frequency sinusoids summed into the displacement field
SHAPE_WAVELENGTH_M = (0.08, 0.25)
FOREGROUND_FRACTION = 0.005
GENERIC_FOV_DEG = 15.0


def subject_rng(seed: int, subject: str) -> np.random.Generator:
    """The degradation's random stream of one subject."""
    return np.random.default_rng([int(seed), zlib.crc32(subject.encode("utf-8"))])


def smooth_displacement(vertices: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(V, 3) a smooth random displacement of (V, 3) vertices with ``SHAPE_RMS_M`` RMS length per vertex."""
    field = np.zeros_like(vertices, dtype=np.float64)
    for _ in range(SHAPE_WAVES):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        wavelength = rng.uniform(*SHAPE_WAVELENGTH_M)
        phase = rng.uniform(0, 2 * np.pi)
        amplitude = rng.normal(size=3)
        field += np.sin(2 * np.pi * (vertices @ direction) / wavelength + phase)[:, None] * amplitude
    rms = float(np.sqrt((field**2).sum(axis=1).mean()))
    return field * (SHAPE_RMS_M / max(rms, 1e-12))


def rotation_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    cross = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def monocular_mesh(vertices: np.ndarray, w2c: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(V, 3) canonical vertices as a monocular tracker would give them from camera ``w2c`` (4, 4):
    smooth shape error, a small rotation about the mesh centre, a shift along the optical axis."""
    vertices = np.asarray(vertices, dtype=np.float64)
    centre = vertices.mean(axis=0)
    shaped = vertices + smooth_displacement(vertices, rng)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rotation = rotation_matrix(axis, np.deg2rad(rng.normal(0.0, ROTATION_SIGMA_DEG)))
    rotated = (shaped - centre) @ rotation.T + centre
    optical_axis = np.asarray(w2c, dtype=np.float64)[2, :3]  # the camera's +z in canonical space
    return rotated + rng.normal(0.0, DEPTH_SIGMA_M) * optical_axis


def foreground_mask(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 foreground estimate of one linear RGB image (H, W, 3), from its pixels alone."""
    import cv2
    from scipy.ndimage import binary_fill_holes

    luminance = np.asarray(image, dtype=np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    level = float(np.percentile(luminance, 99))
    bright = (luminance > FOREGROUND_FRACTION * level).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    if count <= 1:
        return bright.astype(np.float32)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return binary_fill_holes(labels == largest).astype(np.float32)


def generic_focal_camera(
    K: np.ndarray, w2c: np.ndarray, width: int, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), w2c (4, 4)) with the generic focal length and the camera moved along its optical axis
    so that ``centre`` (3,) keeps its image position and size to first order."""
    K = np.asarray(K, dtype=np.float64).copy()
    w2c = np.asarray(w2c, dtype=np.float64).copy()
    focal = 0.5 * width / np.tan(np.deg2rad(GENERIC_FOV_DEG) / 2)
    depth = float(w2c[2, :3] @ centre + w2c[2, 3])
    ratio = focal / float(K[0, 0])
    w2c[2, 3] += (ratio - 1.0) * depth  # camera-space z of every point grows by (ratio - 1) · depth
    K[0, 0] = K[1, 1] = focal
    return K, w2c


def monocular_views(views: FitViews, seed: int) -> tuple[FitViews, dict]:
    """A one-view FitViews as a single-image fit would have it (mesh, mask, focal as described above),
    and a JSON-ready record of what was changed."""
    if len(views) != 1:
        raise ValueError(f"a single-image fit has one view, got {len(views)}")
    rng = subject_rng(seed, views.subject)
    w2c = views.w2c[0].double().numpy()
    K = views.K[0].double().numpy()
    height, width = views.images.shape[-2:]
    record = {
        "mask": "foreground of the input image alone",
        "focal": {"generic_fov_deg": GENERIC_FOV_DEG, "true_px": float(K[0, 0])},
    }
    tracked = None
    centre = np.zeros(3)
    if views.tracked_vertices is not None:
        true_vertices = views.tracked_vertices.double().numpy()
        degraded = monocular_mesh(true_vertices, w2c, rng)
        error = np.sqrt(((degraded - true_vertices) ** 2).sum(axis=1))
        record["mesh"] = {
            "source": "tracked mesh degraded to a monocular tracker's error",
            "shape_rms_m": SHAPE_RMS_M,
            "rotation_sigma_deg": ROTATION_SIGMA_DEG,
            "depth_sigma_m": DEPTH_SIGMA_M,
            "vertex_rms_error_m": round(float(np.sqrt((error**2).mean())), 5),
        }
        tracked = torch.from_numpy(degraded.astype(np.float32))
        centre = degraded.mean(axis=0)
    else:
        record["mesh"] = {"source": "none (the dataset has no tracked mesh)"}
    K_generic, w2c_generic = generic_focal_camera(K, w2c, int(width), centre)
    record["focal"]["generic_px"] = round(float(K_generic[0, 0]), 3)
    mask = foreground_mask(views.images[0].permute(1, 2, 0).numpy())
    changed = dataclasses.replace(
        views,
        masks=torch.from_numpy(mask)[None, None],
        K=torch.from_numpy(K_generic[None].astype(np.float32)),
        w2c=torch.from_numpy(w2c_generic[None].astype(np.float32)),
        tracked_vertices=tracked,
    )
    return changed, record
