"""Shared ingest image steps: projection, crop box, undistort+crop+resize, mesh silhouette mask."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import trimesh

from relightanyone.ingest.steps import (
    MeshSilhouette,
    crop_box_around_points,
    crop_resize_intrinsics,
    load_silhouette_kernel,
    mesh_mask,
    project_points,
    undistort_crop_resize,
)
from relightanyone.render.camera import look_at_w2c

K_SRC = np.array([[520.0, 0.0, 318.3], [0.0, 524.0, 236.9], [0.0, 0.0, 1.0]])
DIST = np.array([-0.21, 0.06, 0.0012, -0.0017, -0.008])
W_SRC, H_SRC = 640, 480


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV w2c for a camera at ``eye`` looking at ``target`` with world +y up in the image."""
    return look_at_w2c(eye, target, (0.0, 1.0, 0.0))


def _undistort_pixels(pixels: np.ndarray, K: np.ndarray = K_SRC, dist: np.ndarray = DIST) -> np.ndarray:
    """Exact (iterated to convergence) undistortion of source pixels into the pinhole camera ``K``."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    out = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, dist, None, None, K, criteria)
    return out.reshape(-1, 2)


def test_project_points_pinhole_known_value():
    w2c = np.eye(4)
    w2c[:3, 3] = [0.1, -0.2, 2.0]
    px = project_points(np.array([[0.0, 0.0, 0.0], [0.4, 0.2, 2.0]]), K_SRC, w2c)
    assert px == pytest.approx(
        np.array([[318.3 + 520 * 0.05, 236.9 - 524 * 0.1], [318.3 + 520 * 0.125, 236.9]])
    )


def test_crop_box_is_square_contains_points_and_is_deterministic():
    pixels = np.array([[100.2, 50.0], [180.7, 210.4], [140.0, 120.0]])
    box = crop_box_around_points(pixels, (W_SRC, H_SRC), margin=0.1)
    x0, y0, x1, y1 = box
    assert x1 - x0 == y1 - y0 == int(np.ceil(160.4 * 1.2))
    assert x0 <= 100.2 - 0.1 * 160.4 + 1 and x1 - 1 >= 180.7 + 0.1 * 160.4 - 1
    assert y0 <= 50.0 - 16.0 and y1 - 1 >= 210.4 + 16.0 - 1
    assert crop_box_around_points(pixels[::-1].copy(), (W_SRC, H_SRC), margin=0.1) == box
    assert all(isinstance(v, int) for v in box)


def test_crop_box_may_leave_the_image_but_must_overlap_it():
    box = crop_box_around_points(np.array([[-20.0, 10.0], [30.0, 60.0]]), (W_SRC, H_SRC), margin=0.0)
    assert box[0] < 0
    with pytest.raises(ValueError, match="does not overlap"):
        crop_box_around_points(np.array([[-500.0, 10.0], [-400.0, 60.0]]), (W_SRC, H_SRC))
    with pytest.raises(ValueError, match="no finite"):
        crop_box_around_points(np.full((3, 2), np.nan), (W_SRC, H_SRC))


def test_crop_resize_intrinsics_follow_the_conventions():
    K_new = crop_resize_intrinsics(K_SRC, (100, 20, 300, 220), 100)
    # crop: c -= (100, 20); resize by 0.5: f *= 0.5, c = (c + 0.5) * 0.5 - 0.5
    assert K_new == pytest.approx(
        np.array([[260.0, 0, (218.3 + 0.5) * 0.5 - 0.5], [0, 262.0, (216.9 + 0.5) * 0.5 - 0.5], [0, 0, 1]])
    )
    with pytest.raises(ValueError, match="square"):
        crop_resize_intrinsics(K_SRC, (0, 0, 10, 20), 16)


def test_new_camera_projects_vertices_where_the_source_pixels_land():
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-0.12, 0.12, size=(200, 3))
    w2c = _look_at(np.array([0.05, 0.02, 0.9]), np.zeros(3))
    src_px = project_points(vertices, K_SRC, w2c, DIST)
    box = crop_box_around_points(src_px, (W_SRC, H_SRC), margin=0.1)
    _, K_new = undistort_crop_resize(np.zeros((H_SRC, W_SRC, 3), np.float32), K_SRC, DIST, box, 128)
    new_px = project_points(vertices, K_new, w2c)
    # Map the distorted source pixel through undistortion, then the crop and resize conventions.
    scale = 128 / (box[2] - box[0])
    expected = (_undistort_pixels(src_px) - [box[0], box[1]] + 0.5) * scale - 0.5
    assert np.abs(new_px - expected).max() < 1e-3


def test_resampled_pixels_hold_the_source_content_they_should():
    # Source channels store their own pixel coordinates; bilinear sampling of a linear ramp is exact.
    v, u = np.mgrid[0:H_SRC, 0:W_SRC].astype(np.float32)
    coords = np.stack([u, v, np.ones_like(u)], axis=-1)
    box = (150, 90, 350, 290)  # 200 px side to 200 px: no supersampling, one remap
    out, K_new = undistort_crop_resize(coords, K_SRC, DIST, box, 200)
    assert out.dtype == np.float32 and out.shape == (200, 200, 3)
    vo, uo = np.mgrid[0:200, 0:200].astype(np.float64)
    rays = np.stack([uo.ravel(), vo.ravel(), np.ones(uo.size)], axis=1) @ np.linalg.inv(K_new).T
    expected = project_points(rays, K_SRC, np.eye(4), DIST).reshape(200, 200, 2)
    assert np.abs(out[..., :2] - expected).max() < 5e-3


def _render_checkerboard(square: float) -> np.ndarray:
    """Distorted source view of a checkerboard drawn in the undistorted normalised image plane (4×4 AA).

    The (smooth) undistortion is solved exactly on a 16 px grid and spline-interpolated to the 4×
    supersampled pixel centres (interpolation error ~1e-6 px), which keeps the render fast.
    """
    from scipy.interpolate import RectBivariateSpline

    grid_x = np.arange(-16.0, W_SRC + 17, 16)
    grid_y = np.arange(-16.0, H_SRC + 17, 16)
    gx, gy = np.meshgrid(grid_x, grid_y)
    und = _undistort_pixels(np.stack([gx.ravel(), gy.ravel()], axis=1)).reshape(len(grid_y), len(grid_x), 2)
    ss = 4
    fine_x = (np.arange(W_SRC * ss) + 0.5) / ss - 0.5
    fine_y = (np.arange(H_SRC * ss) + 0.5) / ss - 0.5
    xn = RectBivariateSpline(grid_y, grid_x, (und[..., 0] - K_SRC[0, 2]) / K_SRC[0, 0])(fine_y, fine_x)
    yn = RectBivariateSpline(grid_y, grid_x, (und[..., 1] - K_SRC[1, 2]) / K_SRC[1, 1])(fine_y, fine_x)
    board = ((np.floor(xn / square) + np.floor(yn / square)) % 2).astype(np.float32)
    return cv2.resize(board, (W_SRC, H_SRC), interpolation=cv2.INTER_AREA)


def test_checkerboard_corners_stay_at_predicted_places_after_downscale():
    square = 0.08
    source = _render_checkerboard(square)
    box = (140, 60, 500, 420)  # 360 px side to 120 px: 3× supersampled area averaging
    out, K_new = undistort_crop_resize(source, K_SRC, DIST, box, 120)
    assert out.shape == (120, 120) and out.dtype == np.float32
    grid = np.arange(-2, 3) * square
    corners_n = np.array([[x, y, 1.0] for x in grid for y in grid])
    predicted = (corners_n @ K_new.T)[:, :2]
    inside = np.all((predicted > 8) & (predicted < 112), axis=1)
    assert inside.sum() >= 9
    start = (predicted[inside] + [0.6, -0.5]).astype(np.float32).reshape(-1, 1, 2)
    refined = cv2.cornerSubPix(
        out, start, (4, 4), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    )
    error = refined.reshape(-1, 2) - predicted[inside]
    # cornerSubPix itself is good to ~0.1 px here; a half-pixel convention slip would show as a 0.3+ bias.
    assert np.abs(error).max() < 0.2
    assert np.abs(error.mean(axis=0)).max() < 0.08


def test_alpha_maps_stay_uint8_and_outside_pixels_are_zero():
    alpha = np.full((H_SRC, W_SRC), 200, np.uint8)
    box = (-100, 100, 200, 400)  # left third lies outside the image
    out, _ = undistort_crop_resize(alpha, K_SRC, None, box, 30)
    assert out.dtype == np.uint8 and out.shape == (30, 30)
    assert np.all(out[:, :9] == 0) and np.all(out[:, 11:] == 200)


def test_undistort_crop_resize_rejects_bad_inputs():
    img = np.zeros((10, 10), np.float32)
    with pytest.raises(ValueError, match="dtype"):
        undistort_crop_resize(img.astype(np.int64), K_SRC, None, (0, 0, 10, 10), 5)
    with pytest.raises(ValueError, match="skew"):
        undistort_crop_resize(
            img, K_SRC + np.array([[0, 1.0, 0], [0, 0, 0], [0, 0, 0]]), None, (0, 0, 10, 10), 5
        )
    with pytest.raises(ValueError, match="coefficients"):
        undistort_crop_resize(img, K_SRC, [0.1, 0.2, 0.3], (0, 0, 10, 10), 5)


def _analytic_sphere_hits(K, w2c, size, radius):
    """Per-pixel first hit point of a ray with the origin-centred sphere (NaN where missed)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    dirs = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ np.linalg.inv(K).T @ w2c[:3, :3]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origin = -w2c[:3, :3].T @ w2c[:3, 3]
    b = dirs @ origin
    disc = b**2 - (origin @ origin - radius**2)
    t = -b - np.sqrt(np.where(disc >= 0, disc, np.nan))
    return (origin + t[:, None] * dirs).reshape(size, size, 3)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_mesh_mask_of_a_sphere_matches_the_analytic_disc_and_cuts_the_neck():
    radius, size = 0.1, 128
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    K = np.array([[300.0, 0, 63.5], [0, 300.0, 60.0], [0, 0, 1]])
    w2c = _look_at(np.array([0.0, 0.1, 0.5]), np.zeros(3))
    hits = _analytic_sphere_hits(K, w2c, size, radius)
    disc = np.isfinite(hits[..., 0])
    full = mesh_mask(sphere.vertices, sphere.faces, None, K, w2c, size)
    assert full.shape == (size, size) and full.dtype == bool
    assert _iou(full, disc) > 0.99
    neck_faces = sphere.triangles_center[:, 1] < -0.03
    cut = mesh_mask(sphere.vertices, sphere.faces, neck_faces, K, w2c, (size, size))
    expected_cut = disc & (np.nan_to_num(hits[..., 1], nan=-1) >= -0.03)
    assert _iou(cut, expected_cut) > 0.97
    assert cut.sum() < full.sum() * 0.9


def test_mesh_mask_validates_the_neck_mask_length():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ValueError, match="neck_face_mask"):
        mesh_mask(sphere.vertices, sphere.faces, np.zeros(3, bool), K_SRC, np.eye(4), 8)


def test_strong_downscale_area_averages_instead_of_aliasing():
    stripes = np.zeros((H_SRC, W_SRC), np.float32)
    stripes[:, ::2] = 1.0  # one-pixel stripes: the worst case for point sampling
    out, _ = undistort_crop_resize(stripes, K_SRC, None, (100, 100, 420, 420), 40)  # 8× smaller
    assert out.mean() == pytest.approx(0.5, abs=0.01)
    assert out.std() < 0.02


def test_real_ava256_camera_crop_is_consistent(real_fixtures):
    import json

    item = json.loads((real_fixtures / "ava-256" / "camera_calibration.json").read_text())["KRT"][0]
    K = np.array(item["K"]).T  # stored transposed
    dist = np.array(item["distortion"] + [0.0])
    w2c = np.vstack([np.array(item["T"])[:4, :3].T, [0, 0, 0, 1]])  # stored transposed, mm
    rng = np.random.default_rng(5)
    points_cam = np.column_stack([rng.uniform(-110, 110, (300, 2)), rng.uniform(900, 1100, 300)])
    points = (points_cam - w2c[:3, 3]) @ w2c[:3, :3]  # camera -> world
    src_px = project_points(points, K, w2c, dist)
    box = crop_box_around_points(src_px, (2668, 4096))
    out, K_new = undistort_crop_resize(np.zeros((4096, 2668), np.uint8), K, dist, box, 128)
    assert out.shape == (128, 128)
    expected = (_undistort_pixels(src_px, K, dist) - [box[0], box[1]] + 0.5) * (128 / (box[2] - box[0])) - 0.5
    assert np.abs(project_points(points, K_new, w2c) - expected).max() < 1e-3


def test_mesh_mask_is_empty_for_a_mesh_outside_or_behind_the_view():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    beside = _look_at(np.array([2.0, 0.0, 0.5]), np.array([2.0, 0.0, 0.0]))  # looks past the sphere
    assert not mesh_mask(sphere.vertices, sphere.faces, None, K, beside, 64).any()
    behind = _look_at(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 1.0]))  # sphere behind the camera
    assert not mesh_mask(sphere.vertices, sphere.faces, None, K, behind, 64).any()
    straddling = _look_at(np.array([0.0, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))  # camera inside the sphere
    assert mesh_mask(sphere.vertices, sphere.faces, None, K, straddling, 64).all()


def _every_pixel_ray_cast(mesh: trimesh.Trimesh, neck: np.ndarray, K, w2c, size: int) -> np.ndarray:
    """The mask rule with one ray through every pixel centre, no culling."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    dirs = pix @ np.linalg.inv(K).T @ w2c[:3, :3]
    origins = np.broadcast_to(-w2c[:3, :3].T @ w2c[:3, 3], dirs.shape)
    first = mesh.ray.intersects_first(ray_origins=np.ascontiguousarray(origins), ray_directions=dirs)
    keep = first >= 0
    keep[keep] = ~neck[first[keep]]
    return keep.reshape(size, size)


@pytest.mark.parametrize(
    ("method", "direct_cast_pixels"),
    [("rays", 16384), ("rays", 0), ("depth-buffer", 0)],
    ids=["rays-hull", "rays-hull+contour-blocks", "depth-buffer"],
)
def test_silhouette_equals_one_ray_per_pixel(monkeypatch, method, direct_cast_pixels):
    # An uneven head-like shape (a bumpy ellipsoid with a "neck" band), seen from many sides and
    # distances, some views cropped so the head leaves the image: the culled cast (every candidate cast, or
    # one ray per block away from the contour edges) and the depth buffer both equal the full cast.
    if method == "depth-buffer" and load_silhouette_kernel() is None:
        pytest.skip("the mesh-silhouette kernel could not be built here (no C++ compiler)")
    monkeypatch.setattr("relightanyone.ingest.steps.DIRECT_CAST_PIXELS", direct_cast_pixels)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    rng = np.random.default_rng(3)
    bumps = 1.0 + 0.15 * np.sin(7 * sphere.vertices[:, 0] / 0.1) * np.cos(5 * sphere.vertices[:, 1] / 0.1)
    vertices = sphere.vertices * bumps[:, None] * [0.8, 1.2, 0.9]
    neck = sphere.triangles_center[:, 1] < -0.04
    silhouette = MeshSilhouette(vertices, sphere.faces, neck, method=method)
    mesh = trimesh.Trimesh(vertices, sphere.faces, process=False)
    for _ in range(16):
        direction = rng.normal(size=3)
        eye = direction / np.linalg.norm(direction) * rng.uniform(0.25, 0.8)
        w2c = _look_at(eye, rng.normal(size=3) * 0.05)
        size = int(rng.choice([48, 64, 97, 130]))  # not all multiples of the block side
        focal = size * rng.uniform(0.8, 2.5)
        K = np.array([[focal, 0, size / 2 + rng.uniform(-30, 30)], [0, focal, size / 2], [0, 0, 1]])
        expected = _every_pixel_ray_cast(mesh, neck, K, w2c, size)
        assert np.array_equal(silhouette.mask(K, w2c, size), expected)
        assert expected.any()


def test_depth_buffer_silhouette_refuses_a_mesh_around_the_camera_and_auto_casts_rays():
    if load_silhouette_kernel() is None:
        pytest.skip("the mesh-silhouette kernel could not be built here (no C++ compiler)")
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    inside = _look_at(np.array([0.0, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="in front of the camera"):
        MeshSilhouette(sphere.vertices, sphere.faces, method="depth-buffer").mask(K, inside, 64)
    assert MeshSilhouette(sphere.vertices, sphere.faces).mask(K, inside, 64).all()
    with pytest.raises(ValueError, match="method must be one of"):
        MeshSilhouette(sphere.vertices, sphere.faces, method="zbuffer")


def test_silhouette_without_a_compiler_warns_and_casts_rays(tmp_path, monkeypatch):
    monkeypatch.setenv("RELIGHTANYONE_CACHE", str(tmp_path))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    load_silhouette_kernel.cache_clear()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
            K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
            w2c = _look_at(np.array([0.0, 0.1, 0.5]), np.zeros(3))
            fallback = MeshSilhouette(sphere.vertices, sphere.faces).mask(K, w2c, 64)
        assert any("cast one ray per pixel instead" in str(w.message) for w in caught)
        rays = MeshSilhouette(sphere.vertices, sphere.faces, method="rays").mask(K, w2c, 64)
        assert np.array_equal(fallback, rays) and rays.any()
    finally:
        load_silhouette_kernel.cache_clear()


def test_undistorted_crop_is_sliced_with_the_values_a_remap_gives():
    """Without distortion the crop is sliced instead of remapped; the pixels must be the remap's."""
    from relightanyone.ingest.steps import _resample, crop_resize_intrinsics

    rng = np.random.default_rng(3)
    image = rng.random((H_SRC, W_SRC, 3), dtype=np.float32)
    for box in [
        (150, 90, 350, 290),
        (-40, -30, 170, 180),
        (W_SRC - 100, H_SRC - 120, W_SRC + 60, H_SRC + 40),
    ]:
        side = box[2] - box[0]
        out, K_new = undistort_crop_resize(image, K_SRC, None, box, 64)
        remapped, _ = _resample(
            image, K_SRC, np.zeros(0), crop_resize_intrinsics(K_SRC, box, side), side, False
        )
        expected = cv2.resize(remapped, (64, 64), interpolation=cv2.INTER_AREA)
        assert np.abs(out - expected).max() < 1e-5
        assert np.allclose(K_new, crop_resize_intrinsics(K_SRC, box, 64))
