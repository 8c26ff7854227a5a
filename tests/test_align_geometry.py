"""Geometry maths: similarities, Umeyama, units, head-pose folding, cameras and lights into canonical space."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relightanyone.align.geometry import (
    MM_TO_M,
    camera_centre,
    decompose_similarity,
    estimate_canonical_from_mesh,
    fold_head_pose,
    invert_similarity,
    light_intensities_to_canonical,
    lights_to_canonical,
    similarity,
    transform_points,
    umeyama,
    w2c_to_canonical,
)
from relightanyone.ingest.steps import project_points

R_A = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
R_B = Rotation.from_euler("zyx", [-10, 80, 5], degrees=True).as_matrix()
K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])


def _rigid(R: np.ndarray, t) -> np.ndarray:
    return similarity(1.0, R, np.asarray(t, dtype=float))


def test_similarity_known_value_and_decomposition():
    T = similarity(2.0, R_A, [1.0, 2.0, 3.0])
    assert transform_points(T, [1.0, 0.0, 0.0]) == pytest.approx(2.0 * R_A[:, 0] + [1, 2, 3])
    scale, R, t = decompose_similarity(T)
    assert scale == pytest.approx(2.0) and R == pytest.approx(R_A) and t == pytest.approx([1, 2, 3])
    assert invert_similarity(T) @ T == pytest.approx(np.eye(4), abs=1e-12)


def test_similarity_rejects_reflections_and_shears():
    with pytest.raises(ValueError, match="proper rotation"):
        similarity(1.0, np.diag([1.0, 1.0, -1.0]))
    shear = np.eye(4)
    shear[0, 1] = 0.3
    with pytest.raises(ValueError, match="not a similarity"):
        decompose_similarity(shear)
    with pytest.raises(ValueError, match="positive"):
        similarity(0.0)


def test_mm_to_m_is_a_scale_similarity():
    assert MM_TO_M == 1e-3
    assert transform_points(similarity(MM_TO_M), [[120.0, -45.0, 988.0]]) == pytest.approx(
        np.array([[0.12, -0.045, 0.988]])
    )


def test_umeyama_recovers_a_similarity_and_a_rigid_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    T = similarity(0.37, R_B, [0.1, -2.0, 5.0])
    dst = transform_points(T, src)
    assert umeyama(src, dst) == pytest.approx(T, abs=1e-10)
    rigid = _rigid(R_B, [0.1, -2.0, 5.0])
    assert umeyama(src, transform_points(rigid, src), with_scale=False) == pytest.approx(rigid, abs=1e-10)
    with pytest.raises(ValueError, match="collinear"):
        umeyama(np.outer(np.arange(5.0), [1, 1, 1]), np.outer(np.arange(5.0), [1, 1, 1]))


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    dst = src * [1.0, 1.0, -1.0]  # mirrored data: best proper rotation, never det -1
    T = umeyama(src, dst)
    assert np.linalg.det(T[:3, :3]) > 0


def test_fold_head_pose_matches_projecting_posed_vertices():
    rng = np.random.default_rng(2)
    head_vertices = rng.uniform(-90, 90, size=(30, 3))  # mm, head space
    head_to_world = _rigid(R_A, [30.0, -1500.0, 200.0])[:3]  # Ava-256 head_pose txt is 3x4
    w2c_world = _rigid(R_B, [0.0, 0.0, 0.0])
    w2c_world[:3, 3] = -R_B @ transform_points(head_to_world, [0.0, 0.0, 0.0]) + [0, 0, 1000.0]
    world_vertices = transform_points(head_to_world, head_vertices)
    w2c_head = fold_head_pose(w2c_world, head_to_world)
    assert project_points(head_vertices, K, w2c_head) == pytest.approx(
        project_points(world_vertices, K, w2c_world)
    )
    with pytest.raises(ValueError, match="rigid"):
        fold_head_pose(w2c_world, similarity(2.0, R_A))


def test_w2c_to_canonical_stays_rigid_and_keeps_every_pixel():
    rng = np.random.default_rng(3)
    native_points = rng.uniform(-100, 100, size=(25, 3))  # mm in a native frame
    w2c_native = _rigid(R_B, [10.0, -20.0, 900.0])
    canonical_from_native = similarity(MM_TO_M * 1.07, R_A, [0.01, 0.02, -0.03])
    w2c_c = w2c_to_canonical(w2c_native, canonical_from_native)
    scale, R, _ = decompose_similarity(w2c_c)
    assert scale == pytest.approx(1.0, abs=1e-12) and R @ R.T == pytest.approx(np.eye(3), abs=1e-12)
    canonical_points = transform_points(canonical_from_native, native_points)
    assert project_points(canonical_points, K, w2c_c) == pytest.approx(
        project_points(native_points, K, w2c_native), abs=1e-9
    )
    # Closed form: [R_w R^T | s t_w - R_w R^T t]
    s, Rc, tc = decompose_similarity(canonical_from_native)
    assert w2c_c[:3, 3] == pytest.approx(s * w2c_native[:3, 3] - R_B @ Rc.T @ tc)
    # The camera sits at the canonical image of its native centre, in metres.
    assert camera_centre(w2c_c) == pytest.approx(
        transform_points(canonical_from_native, camera_centre(w2c_native))
    )


def test_lights_move_with_the_rig_and_intensities_keep_irradiance():
    positions_mm = np.array([[1000.0, 0.0, 0.0], [0.0, 1707.0, 0.0]])
    canonical_from_native = similarity(MM_TO_M, R_A, [0.0, 0.1, 0.0])
    positions = lights_to_canonical(positions_mm, canonical_from_native)
    assert np.linalg.norm(positions[1] - [0.0, 0.1, 0.0]) == pytest.approx(1.707)
    intensity_native = np.array([[1.0e6, 1.0e6, 1.0e6], [2.0e6, 2.0e6, 2.0e6]])  # defined per mm²
    intensity = light_intensities_to_canonical(intensity_native, canonical_from_native)
    point_native = np.array([0.0, 0.0, 0.0])
    point = transform_points(canonical_from_native, point_native)
    irr_native = intensity_native[:, 0] / np.sum((positions_mm - point_native) ** 2, axis=1)
    irr = intensity[:, 0] / np.sum((positions - point) ** 2, axis=1)
    assert irr == pytest.approx(irr_native)
    with pytest.raises(ValueError, match="non-negative"):
        light_intensities_to_canonical([-1.0], canonical_from_native)


def test_estimate_canonical_from_mesh_recovers_the_tracker_frame():
    rng = np.random.default_rng(4)
    template = rng.uniform(-0.1, 0.1, size=(100, 3))  # canonical metres
    native_from_canonical = similarity(1000.0, R_B, [5.0, 1600.0, -30.0])  # tracker in mm
    tracked = transform_points(native_from_canonical, template)
    tracked[:10] += rng.normal(scale=50.0, size=(10, 3))  # a moving jaw, excluded by the mask
    mask = np.ones(100, bool)
    mask[:10] = False
    T = estimate_canonical_from_mesh(tracked, template, vertex_mask=mask)
    assert T == pytest.approx(invert_similarity(native_from_canonical), abs=1e-9)
    with pytest.raises(ValueError, match="must match"):
        estimate_canonical_from_mesh(tracked[:50], template)
