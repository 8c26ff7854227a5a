"""Cameras: projection against OpenCV and gsplat, round trips, resize/crop/world edits, batching."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from relightanyone.render.camera import (
    Cameras,
    crop_intrinsics,
    look_at_w2c,
    resize_intrinsics,
    rigid_inverse,
    similarity_scale,
)


def random_rig(batch: int = 4, seed: int = 0, n_dist: int = 5, skew: bool = False) -> Cameras:
    """Cameras around the origin looking roughly at it, with random distortion."""
    rng = np.random.default_rng(seed)
    K = np.zeros((batch, 3, 3))
    K[:, 0, 0] = rng.uniform(700, 900, batch)
    K[:, 1, 1] = K[:, 0, 0] * rng.uniform(0.98, 1.02, batch)
    K[:, 0, 2] = rng.uniform(300, 340, batch)
    K[:, 1, 2] = rng.uniform(220, 260, batch)
    K[:, 2, 2] = 1.0
    if skew:
        K[:, 0, 1] = rng.uniform(-3, 3, batch)
    w2c = np.tile(np.eye(4), (batch, 1, 1))
    for b in range(batch):
        w2c[b, :3, :3] = cv2.Rodrigues(rng.normal(size=3) * 0.3)[0]
        w2c[b, :3, 3] = rng.normal(size=3) * 0.05 + [0.0, 0.0, 2.0]
    scales = np.array([0.1, 0.05, 0.005, 0.005, 0.02, 0.05, 0.02, 0.01])[:n_dist]
    dist = rng.normal(size=(batch, n_dist)) * scales
    return Cameras.create(
        torch.tensor(K), torch.tensor(w2c), 640, 480, torch.tensor(dist), [f"c{b}" for b in range(batch)]
    )


def random_points(n: int = 200, seed: int = 1) -> torch.Tensor:
    return torch.tensor(np.random.default_rng(seed).normal(size=(n, 3)) * 0.25)


def cv2_project(cams: Cameras, points: torch.Tensor) -> np.ndarray:
    out = []
    for b in range(len(cams)):
        rvec = cv2.Rodrigues(cams.R[b].numpy())[0]
        uv, _ = cv2.projectPoints(
            points.numpy(), rvec, cams.t[b].numpy(), cams.K[b].numpy(), cams.dist[b].numpy()
        )
        out.append(uv[:, 0])
    return np.stack(out)


@pytest.mark.parametrize("n_dist", [4, 5, 8])
def test_project_matches_cv2_project_points(n_dist: int) -> None:
    cams = random_rig(n_dist=n_dist)
    points = random_points()
    uv, depth = cams.project(points)
    assert uv.shape == (4, 200, 2) and depth.shape == (4, 200)
    np.testing.assert_allclose(uv.numpy(), cv2_project(cams, points), atol=1e-6, rtol=0)
    expected_depth = (cams.world_to_camera(points))[..., 2]
    assert torch.equal(depth, expected_depth) and bool((depth > 1.0).all())


def test_project_batched_points_and_skew() -> None:
    cams = random_rig(skew=True)
    points = random_points().expand(4, -1, -1) + torch.linspace(0, 0.1, 4, dtype=torch.float64)[:, None, None]
    uv, _ = cams.project(points)
    # Skew adds s * y_distorted to u; subtracting it must give OpenCV's answer, which ignores K[0, 1].
    no_skew_K = cams.K.clone()
    no_skew_K[:, 0, 1] = 0
    plain = Cameras(no_skew_K, cams.w2c, cams.dist, cams.width, cams.height)
    uv_plain, _ = plain.project(points)
    y_distorted = (uv_plain[..., 1] - cams.K[:, None, 1, 2]) / cams.K[:, None, 1, 1]
    torch.testing.assert_close(uv[..., 0], uv_plain[..., 0] + cams.K[:, None, 0, 1] * y_distorted)
    for b in range(4):
        ref = cv2_project(plain[b], points[b])[0]
        np.testing.assert_allclose(uv_plain[b].numpy(), ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("skew", [False, True])
def test_unproject_round_trips_project(skew: bool) -> None:
    cams = random_rig(n_dist=8, skew=skew)
    points = random_points()
    uv, depth = cams.project(points)
    back = cams.unproject(uv, depth)
    torch.testing.assert_close(back, points.expand(4, -1, -1), atol=1e-9, rtol=0)


def test_pixels_to_normalized_matches_cv2_undistort_points() -> None:
    cams = random_rig()
    pixels = torch.tensor(np.random.default_rng(3).uniform([0, 0], [640, 480], size=(50, 2)))
    ours = cams.pixels_to_normalized(pixels, iterations=5)
    criteria = (cv2.TERM_CRITERIA_COUNT, 5, 0)
    for b in range(len(cams)):
        ref = cv2.undistortPoints(
            pixels.numpy()[:, None], cams.K[b].numpy(), cams.dist[b].numpy(), None, None, None, criteria
        )[:, 0]
        np.testing.assert_allclose(ours[b].numpy(), ref, atol=1e-9, rtol=0)


def test_rays_pass_through_the_projected_points() -> None:
    cams = random_rig()
    points = random_points(20)
    uv, depth = cams.project(points)
    origins, directions = cams.rays(uv)
    torch.testing.assert_close(origins[:, 0], cams.centers)
    to_points = points[None] - origins
    cross = torch.linalg.cross(to_points, directions, dim=-1).norm(dim=-1)
    assert float(cross.max()) < 1e-9


@pytest.mark.parametrize("scale", [0.25, 0.5, 2.0, (333, 250)])
def test_resize_uses_the_half_pixel_rule(scale: float | tuple[int, int]) -> None:
    cams = random_rig(skew=True)
    resized = cams.resize(scale)
    if isinstance(scale, tuple):
        assert resized.width.tolist() == [333] * 4 and resized.height.tolist() == [250] * 4
        sx, sy = 333 / 640, 250 / 480
    else:
        assert resized.width.tolist() == [round(640 * scale)] * 4
        sx = sy = scale
    points = random_points()
    uv, _ = cams.project(points)
    uv_resized, _ = resized.project(points)
    expected = torch.stack([(uv[..., 0] + 0.5) * sx - 0.5, (uv[..., 1] + 0.5) * sy - 0.5], dim=-1)
    torch.testing.assert_close(uv_resized, expected, atol=1e-9, rtol=0)
    assert torch.equal(resized.w2c, cams.w2c) and torch.equal(resized.dist, cams.dist)


def test_crop_shifts_the_principal_point() -> None:
    cams = random_rig()
    cropped = cams.crop(100, 40, 256, 300)
    uv, _ = cams.project(random_points())
    uv_crop, _ = cropped.project(random_points())
    torch.testing.assert_close(
        uv_crop, uv - torch.tensor([100.0, 40.0], dtype=torch.float64), atol=1e-9, rtol=0
    )
    assert cropped.width.tolist() == [256] * 4 and cropped.height.tolist() == [300] * 4
    # Crop then resize equals the composition of both pixel maps.
    both = cropped.resize(0.5)
    uv_both, _ = both.project(random_points())
    torch.testing.assert_close(
        uv_both, (uv - torch.tensor([100.0, 40.0], dtype=torch.float64) + 0.5) * 0.5 - 0.5
    )


def test_intrinsics_rules_known_values() -> None:
    K = np.array([[800.0, 2.0, 319.5], [0.0, 820.0, 239.5], [0.0, 0.0, 1.0]])
    # Resize 640x480 -> 320x120: the image centre stays the image centre, focals and skew scale per axis.
    np.testing.assert_array_equal(
        resize_intrinsics(K, 0.5, 0.25), [[400.0, 1.0, 159.5], [0.0, 205.0, 59.5], [0.0, 0.0, 1.0]]
    )
    np.testing.assert_array_equal(
        crop_intrinsics(K, 100, 40), [[800.0, 2.0, 219.5], [0.0, 820.0, 199.5], [0.0, 0.0, 1.0]]
    )
    assert K[0, 2] == 319.5  # the input is not modified
    # A tensor batch keeps its dtype and takes one factor (or origin) per camera.
    batch = torch.tensor(np.stack([K, K]), dtype=torch.float32)
    resized = resize_intrinsics(batch, torch.tensor([2.0, 0.5]), torch.tensor([2.0, 0.5]))
    assert resized.dtype == torch.float32
    assert resized[:, 0, 2].tolist() == [639.5, 159.5] and resized[:, 1, 1].tolist() == [1640.0, 410.0]
    cropped = crop_intrinsics(batch, torch.tensor([0.0, 10.0]), torch.tensor([5.0, 0.0]))
    assert cropped[:, 0, 2].tolist() == [319.5, 309.5] and cropped[:, 1, 2].tolist() == [234.5, 239.5]


@pytest.mark.parametrize("up", [(0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (0.3, -1.0, 0.2)])
def test_look_at_puts_up_above_the_image_centre(up: tuple[float, float, float]) -> None:
    eye, target = np.array([0.4, 0.3, 1.2]), np.array([0.05, -0.02, 0.1])
    w2c = look_at_w2c(eye, target, up)
    assert np.allclose(w2c[:3, :3] @ w2c[:3, :3].T, np.eye(3)) and np.linalg.det(w2c[:3, :3]) > 0
    K = torch.tensor([[100.0, 0.0, 49.5], [0.0, 100.0, 39.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = Cameras.create(K, torch.tensor(w2c), 100, 80)
    unit_up = np.asarray(up) / np.linalg.norm(up)
    beside = np.cross(target - eye, unit_up)  # to the right of the view, seen from the camera
    points = torch.tensor(np.stack([target, target + 0.05 * unit_up, target + 0.05 * beside]))
    pixels, depth = cams.project(points)
    centre, above, right = pixels[0]
    torch.testing.assert_close(centre, torch.tensor([49.5, 39.5], dtype=torch.float64))
    assert float(above[1]) < 39.5 and float(right[0]) > 49.5 and bool((depth > 0).all())
    with pytest.raises(ValueError, match="parallel to the view direction"):
        look_at_w2c(eye, target, eye - target)


def test_transform_world_keeps_pixels_and_scales_depth() -> None:
    cams = random_rig()
    points = random_points()
    rotation = torch.tensor(cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0])
    S = torch.eye(4, dtype=torch.float64)
    S[:3, :3] = 0.001 * rotation  # e.g. millimetres -> metres plus a rotation
    S[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    moved = cams.transform_world(S)
    new_points = points @ S[:3, :3].T + S[:3, 3]
    uv, depth = cams.project(points)
    uv_new, depth_new = moved.project(new_points)
    torch.testing.assert_close(uv_new, uv, atol=1e-8, rtol=0)
    torch.testing.assert_close(depth_new, depth * 0.001)
    R = moved.R
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    torch.testing.assert_close(moved.centers, cams.centers @ S[:3, :3].T + S[:3, 3])
    with pytest.raises(ValueError, match="uniform scale"):
        cams.transform_world(torch.diag(torch.tensor([1.0, 2.0, 1.0, 1.0], dtype=torch.float64)))


def test_centers_look_dirs_and_c2w() -> None:
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([-2.0, 0.5, 0.0], dtype=torch.float64)
    cams = Cameras.from_c2w(
        torch.eye(3, dtype=torch.float64) * 100 + torch.tensor([[0, 0, 50], [0, 0, 40], [0, 0, -99.0]]),
        c2w,
        100,
        80,
    )
    torch.testing.assert_close(cams.centers[0], c2w[:3, 3])
    torch.testing.assert_close(cams.look_dirs[0], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(cams.c2w[0], c2w)
    # A point one metre in front of the camera lands on the principal point at depth 1.
    uv, depth = cams.project(torch.tensor([[-1.0, 0.5, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(uv[0, 0], torch.tensor([50.0, 40.0], dtype=torch.float64))
    assert float(depth[0, 0]) == pytest.approx(1.0)
    torch.testing.assert_close(rigid_inverse(rigid_inverse(c2w)), c2w)


def test_batching_indexing_cat_and_to() -> None:
    cams = random_rig(batch=5)
    assert len(cams[2]) == 1 and cams[2].names == ("c2",)
    assert cams[-1].names == ("c4",)
    picked = cams[[4, 0]]
    assert picked.names == ("c4", "c0") and torch.equal(picked.K[1], cams.K[0])
    assert cams[1:3].names == ("c1", "c2")
    assert cams[torch.tensor([True, False, True, False, False])].names == ("c0", "c2")
    rational = random_rig(batch=2, n_dist=8)
    joined = Cameras.cat([cams, rational])
    assert len(joined) == 7 and joined.dist.shape == (7, 8)
    assert torch.equal(joined.dist[:5, 5:], torch.zeros(5, 3, dtype=torch.float64))
    uv_joined, _ = joined.project(random_points())
    uv_a, _ = cams.project(random_points())
    torch.testing.assert_close(uv_joined[:5], uv_a)
    single = cams.to(dtype=torch.float32)
    assert (
        single.K.dtype == torch.float32
        and single.w2c.dtype == torch.float32
        and single.width.dtype == torch.int64
    )
    with pytest.raises(IndexError):
        cams[5]


def test_invalid_construction_is_refused() -> None:
    cams = random_rig(batch=2)
    with pytest.raises(ValueError, match="w2c"):
        Cameras(cams.K, cams.w2c[:1], cams.dist, cams.width, cams.height)
    with pytest.raises(ValueError, match="dist"):
        Cameras(cams.K, cams.w2c, cams.dist[:, :4], cams.width, cams.height)
    with pytest.raises(ValueError, match="names"):
        Cameras(cams.K, cams.w2c, cams.dist, cams.width, cams.height, ("only-one",))
    with pytest.raises(ValueError, match="at most 8"):
        Cameras.create(cams.K, cams.w2c, 640, 480, torch.zeros(2, 12))
    with pytest.raises(ValueError, match="similarity"):
        similarity_scale(torch.eye(3))


def test_pinhole_projection_matches_gsplat_torch_reference() -> None:
    from gsplat.cuda._torch_impl import _fully_fused_projection

    pinhole = random_rig(batch=3)
    cams = Cameras(pinhole.K, pinhole.w2c, torch.zeros_like(pinhole.dist), pinhole.width, pinhole.height)
    points = random_points(64).float()
    covars = torch.eye(3).expand(64, 3, 3) * 1e-6
    _, means2d, depths, _, _ = _fully_fused_projection(
        points, covars, cams.to_gsplat_viewmats(), cams.to_gsplat_Ks(), 640, 480
    )
    uv, depth = cams.project(points.double())
    np.testing.assert_allclose(means2d.numpy(), uv.numpy(), atol=2e-3, rtol=0)
    np.testing.assert_allclose(depths.numpy(), depth.numpy(), atol=1e-5, rtol=0)
    assert cams.to_gsplat_viewmats().dtype == torch.float32
