"""Table 2's single-image protocol: monocular-quality mesh, a mask from the image, a generic focal length."""

from __future__ import annotations

import numpy as np
import torch

from relightanyone.evaluation.single_image import (
    GENERIC_FOV_DEG,
    SHAPE_RMS_M,
    foreground_mask,
    generic_focal_camera,
    monocular_mesh,
    monocular_views,
    smooth_displacement,
    subject_rng,
)
from relightanyone.model.fit.views import FitViews
from relightanyone.render.camera import look_at_w2c


def sphere_points(count: int = 400) -> np.ndarray:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(count, 3))
    return 0.1 * points / np.linalg.norm(points, axis=1, keepdims=True)


def test_monocular_mesh_has_the_stated_error_and_is_deterministic_per_subject():
    vertices = sphere_points()
    field = smooth_displacement(vertices, subject_rng(0, "s01"))
    assert np.isclose(np.sqrt((field**2).sum(axis=1).mean()), SHAPE_RMS_M)
    # Smooth: neighbouring vertices move alike (the field is not per-vertex noise).
    nearest = np.argsort(((vertices[:, None] - vertices[None]) ** 2).sum(-1), axis=1)[:, 1]
    assert np.abs(field - field[nearest]).mean() < 0.5 * np.abs(field).mean()
    w2c = look_at_w2c(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    first = monocular_mesh(vertices, w2c, subject_rng(0, "s01"))
    np.testing.assert_array_equal(first, monocular_mesh(vertices, w2c, subject_rng(0, "s01")))
    assert not np.allclose(first, monocular_mesh(vertices, w2c, subject_rng(0, "s02")))
    error = np.sqrt(((first - vertices) ** 2).sum(axis=1).mean())
    assert 0.5 * SHAPE_RMS_M < error < 0.05  # shape error plus a rigid error of millimetres to centimetres


def test_generic_focal_keeps_the_head_centre_in_place():
    K = np.array([[300.0, 0, 31.5], [0, 300.0, 31.5], [0, 0, 1]])
    w2c = look_at_w2c(np.array([0.3, 0.1, 1.2]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    centre = np.array([0.01, 0.02, 0.0])
    K_g, w2c_g = generic_focal_camera(K, w2c, 64, centre)
    assert np.isclose(K_g[0, 0], 32 / np.tan(np.deg2rad(GENERIC_FOV_DEG) / 2)) and K_g[0, 0] == K_g[1, 1]

    def project(K, w2c, point):
        camera = w2c[:3, :3] @ point + w2c[:3, 3]
        return (K @ camera)[:2] / camera[2]

    np.testing.assert_allclose(project(K_g, w2c_g, centre), project(K, w2c, centre), atol=1e-9)
    np.testing.assert_allclose(w2c_g[:3, :3], w2c[:3, :3])


def test_foreground_mask_comes_from_the_image_alone():
    image = np.zeros((32, 32, 3), np.float32)
    y, x = np.mgrid[0:32, 0:32]
    disc = (x - 16) ** 2 + (y - 15) ** 2 < 100
    image[disc] = 0.4
    image[14:17, 14:17] = 0.0  # a dark spot inside the head: filled
    image[1, 30] = 0.5  # a speck away from the head: dropped
    np.testing.assert_array_equal(foreground_mask(image) > 0.5, disc)


def test_monocular_views_replace_mesh_mask_and_focal():
    image = torch.zeros(1, 3, 32, 32)
    image[:, :, 8:24, 10:22] = 0.3
    w2c = look_at_w2c(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    views = FitViews(
        images=image,
        masks=torch.ones(1, 1, 32, 32),
        K=torch.tensor([[[200.0, 0, 15.5], [0, 200.0, 15.5], [0, 0, 1]]]),
        w2c=torch.from_numpy(w2c[None].astype(np.float32)),
        tracked_vertices=torch.from_numpy(sphere_points().astype(np.float32)),
        subject="s01",
        frame=0,
        dataset="d",
        pattern="full",
        keys=["k"],
        cameras=["cam00"],
    )
    changed, record = monocular_views(views, seed=0)
    assert changed.masks.sum() == 16 * 12 and changed.masks[0, 0, 0, 0] == 0
    assert not torch.equal(changed.tracked_vertices, views.tracked_vertices)
    assert changed.K[0, 0, 0] != 200.0 and record["focal"]["true_px"] == 200.0
    assert record["mesh"]["vertex_rms_error_m"] > 0 and record["mask"].startswith("foreground")
    assert torch.equal(changed.images, views.images)
