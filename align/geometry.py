"""Geometry maths: similarity transforms, units, head-pose folding, light rigs into canonical space.

All transforms are 4×4 float64 numpy arrays acting on column vectors ``[x, y, z, 1]``. A *similarity*
``S = [[s R, t], [0, 1]]`` (s > 0, R a proper rotation) maps one frame into another, e.g.
``canonical_from_native``: ``X_canonical = s R X_native + t``. Cameras stay rigid (``w2c`` has a pure
rotation) and in metres; see ``docs/align.md`` for the derivations.
"""

from __future__ import annotations

from typing import Any

import numpy as np

MM_TO_M = 1e-3
CM_TO_M = 1e-2

_ORTHO_TOL = 1e-6
# Checks below compare with max-abs deviations: np.allclose costs ~100 µs per 4×4, and ingest makes
# thousands of these checks per subject.
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


def _as_transform(T: Any, name: str = "transform") -> np.ndarray:
    """Validate a ``(4, 4)`` (or ``(3, 4)``, completed with ``0 0 0 1``) finite affine transform."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape == (3, 4):
        arr = np.vstack([arr, [0.0, 0.0, 0.0, 1.0]])
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must be a 4×4 (or 3×4) matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if np.abs(arr[3] - _LAST_ROW).max() > 1e-5:
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    return arr


def _as_points(points: Any, name: str = "points") -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {arr.shape}")
    return arr


def similarity(scale: float, R: Any = None, t: Any = None) -> np.ndarray:
    """Build ``[[scale R, t], [0, 1]]``.

    Args: scale > 0; R ``(3, 3)`` proper rotation (default identity); t ``(3,)`` (default 0).
    Returns: ``(4, 4)`` float64.
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"similarity scale must be a positive finite number, got {scale}")
    R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    t = np.zeros(3) if t is None else np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R must be (3, 3) and t (3,), got {R.shape} and {t.shape}")
    if np.abs(R @ R.T - _EYE3).max() > _ORTHO_TOL or np.linalg.det(R) <= 0:
        raise ValueError("R is not a proper rotation (orthonormal with determinant +1)")
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = t
    return T


def decompose_similarity(T: Any, atol: float = _ORTHO_TOL) -> tuple[float, np.ndarray, np.ndarray]:
    """Split a similarity ``(4, 4)`` into ``(scale, R (3, 3), t (3,))``; raises if it is not one.

    Scale is the cube root of the determinant of the linear part; the rest must be a proper rotation
    to ``atol`` (relative to the scale).
    """
    T = _as_transform(T, "similarity")
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    if det <= 0:
        raise ValueError(f"similarity has a non-positive determinant ({det:.3g}): reflection or degenerate")
    scale = det ** (1.0 / 3.0)
    R = A / scale
    if np.abs(R @ R.T - _EYE3).max() > atol:
        raise ValueError("transform is not a similarity: its linear part is not a scaled rotation")
    return scale, R, T[:3, 3].copy()


def invert_similarity(T: Any) -> np.ndarray:
    """Exact inverse of a similarity ``(4, 4)``: ``[[R^T / s, -R^T t / s], [0, 1]]``."""
    scale, R, t = decompose_similarity(T)
    return similarity(1.0 / scale, R.T, -(R.T @ t) / scale)


def transform_points(T: Any, points: Any) -> np.ndarray:
    """Apply a 4×4 (or 3×4) affine ``T`` to ``points (..., 3)``; returns ``(..., 3)`` float64."""
    T = _as_transform(T)
    pts = _as_points(points)
    return pts @ T[:3, :3].T + T[:3, 3]


def umeyama(src: Any, dst: Any, with_scale: bool = True, weights: Any = None) -> np.ndarray:
    """Least-squares similarity (Umeyama 1991) with ``dst ≈ T @ src``.

    Args:
        src, dst: ``(N, 3)`` corresponding points, N >= 3 and not collinear.
        with_scale: estimate the scale (else a rigid transform, scale 1).
        weights: optional ``(N,)`` non-negative per-point weights.
    Returns:
        ``(4, 4)`` float64 similarity (always a proper rotation, never a reflection).
    """
    src = _as_points(src, "src")
    dst = _as_points(dst, "dst")
    if src.ndim != 2 or src.shape != dst.shape or src.shape[0] < 3:
        raise ValueError(f"src and dst must be matching (N>=3, 3) arrays, got {src.shape} and {dst.shape}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("src/dst contain NaN or infinite values")
    w = np.ones(src.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (src.shape[0],) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be (N,) non-negative with a positive sum")
    w = w / w.sum()
    mu_src, mu_dst = w @ src, w @ dst
    src_c, dst_c = src - mu_src, dst - mu_dst
    cov = (dst_c * w[:, None]).T @ src_c
    U, D, Vt = np.linalg.svd(cov)
    if D[1] < 1e-12 * max(D[0], 1e-300):
        raise ValueError("points are (nearly) collinear: the rotation is not determined")
    # Flip the smallest singular direction when needed so the result is a rotation, not a reflection.
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ S @ Vt
    if with_scale:
        var_src = float(np.sum(w * np.sum(src_c**2, axis=1)))
        scale = float(np.trace(np.diag(D) @ S)) / var_src
    else:
        scale = 1.0
    return similarity(scale, R, mu_dst - scale * R @ mu_src)


def fold_head_pose(w2c_world: Any, head_to_world: Any) -> np.ndarray:
    """Camera extrinsic in head space: ``w2c_head = w2c_world @ head_to_world``.

    Args:
        w2c_world: ``(4, 4)`` world→camera in the capture's native world frame.
        head_to_world: ``(3, 4)`` or ``(4, 4)`` rigid head pose of one frame (Ava-256 ``head_pose/*.txt``),
            in the same units as ``w2c_world``.
    Returns:
        ``(4, 4)`` head→camera, so that projecting head-space vertices with it equals projecting
        ``head_to_world @ v`` with ``w2c_world``.
    """
    w2c = _as_transform(w2c_world, "w2c_world")
    pose = _as_transform(head_to_world, "head_to_world")
    scale, _, _ = decompose_similarity(pose)
    if abs(scale - 1.0) > 1e-4:
        raise ValueError(f"head pose must be rigid (scale 1), got scale {scale:.6g}")
    return w2c @ pose


def w2c_to_canonical(w2c_native: Any, canonical_from_native: Any) -> np.ndarray:
    """Re-express a rigid native-frame camera in canonical head space, keeping it rigid and metric.

    With ``canonical_from_native = [[s R, t], [0, 1]]`` (``X_c = s R X_n + t``, canonical in metres), the
    camera frame is scaled by the same ``s`` (pixels do not change under a uniform scaling of camera
    coordinates), giving ``w2c_c = diag(s, s, s, 1) @ w2c_n @ canonical_from_native⁻¹``, i.e.
    ``[R_w R^T | s t_w - R_w R^T t]``.

    Args: w2c_native ``(4, 4)`` rigid; canonical_from_native ``(4, 4)`` similarity.
    Returns: ``(4, 4)`` rigid world→camera in canonical metres.
    """
    w2c = _as_transform(w2c_native, "w2c_native")
    cam_scale, _, _ = decompose_similarity(w2c)
    if abs(cam_scale - 1.0) > 1e-4:
        raise ValueError(f"w2c_native must be rigid (scale 1), got scale {cam_scale:.6g}")
    scale, R, t = decompose_similarity(canonical_from_native)
    rotation = w2c[:3, :3] @ R.T
    out = np.eye(4)
    out[:3, 3] = scale * w2c[:3, 3] - rotation @ t
    # Re-orthonormalise against round-off so the stored extrinsic is exactly rigid.
    U, _, Vt = np.linalg.svd(rotation)
    out[:3, :3] = U @ Vt
    return out


def camera_centre(w2c: Any) -> np.ndarray:
    """Camera centre ``(3,)`` in world coordinates of a rigid ``w2c (4, 4)``: ``-R^T t``."""
    w2c = _as_transform(w2c, "w2c")
    return -w2c[:3, :3].T @ w2c[:3, 3]


def lights_to_canonical(positions_native: Any, canonical_from_native: Any) -> np.ndarray:
    """Map light positions ``(L, 3)`` from the native rig frame to canonical space ``(L, 3)`` (metres)."""
    decompose_similarity(canonical_from_native)  # refuse non-similarities: they would bend the rig
    return transform_points(canonical_from_native, positions_native)


def light_intensities_to_canonical(intensities_native: Any, canonical_from_native: Any) -> np.ndarray:
    """Rescale point-light intensities ``(L, 3)`` (or ``(L,)``) for the canonical frame.

    Point-light intensities are defined so that irradiance is ``I / d²`` with ``d`` in canonical metres.
    Distances scale by ``s`` under ``canonical_from_native``, so ``I_c = s² I_n`` keeps the irradiance at
    every point of the head (and therefore every rendered pixel) unchanged.
    """
    scale, _, _ = decompose_similarity(canonical_from_native)
    intensities = np.asarray(intensities_native, dtype=np.float64)
    if not np.all(np.isfinite(intensities)) or np.any(intensities < 0):
        raise ValueError("light intensities must be finite and non-negative")
    return intensities * scale**2


def estimate_canonical_from_mesh(
    tracked_vertices: Any, template_vertices: Any, vertex_mask: Any = None, with_scale: bool = True
) -> np.ndarray:
    """Similarity from a tracker's frame to canonical head space: ``template ≈ T @ tracked`` (Umeyama).

    Args:
        tracked_vertices: ``(V, 3)`` one frame's tracked mesh in the tracker's frame (any units).
        template_vertices: ``(V, 3)`` the same topology in canonical head space (metres).
        vertex_mask: optional ``(V,)`` bool of the vertices to fit on (e.g. the rigid skull, not the jaw).
        with_scale: estimate the scale (native units → metres and any size difference).
    Returns:
        ``(4, 4)`` ``canonical_from_native`` similarity.
    """
    tracked = _as_points(tracked_vertices, "tracked_vertices")
    template = _as_points(template_vertices, "template_vertices")
    if tracked.shape != template.shape:
        raise ValueError(f"tracked {tracked.shape} and template {template.shape} vertices must match")
    if vertex_mask is not None:
        mask = np.asarray(vertex_mask, dtype=bool).reshape(-1)
        if mask.shape != (tracked.shape[0],):
            raise ValueError(f"vertex_mask must be ({tracked.shape[0]},), got {mask.shape}")
        tracked, template = tracked[mask], template[mask]
    return umeyama(tracked, template, with_scale=with_scale)
