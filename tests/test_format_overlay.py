"""The reprojection overlay stays readable at real mesh densities: it draws the outline the camera sees,
not every triangle edge, so the image shows through inside the head."""

from __future__ import annotations

import cv2
import numpy as np

from relightanyone.format.overlay import draw_mesh_over, project
from relightanyone.render.mesh import faces_touching
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.template import make_template


def test_overlay_of_a_dense_mesh_leaves_most_of_the_head_showing():
    template = make_template(112)  # ~9,400 vertices, a real head mesh's density
    assert len(template.vertices) > 7000
    size, scale = 128, 4
    K = np.array([[300.0, 0, size / 2 - 0.5], [0, 300.0, size / 2 - 0.5], [0, 0, 1]])
    w2c = look_at_w2c(np.array([0.2, 0.05, 0.8]), np.zeros(3))
    neck_faces = faces_touching(template.neck_mask.astype(bool), template.faces)
    image = np.full((size, size, 3), 128, np.uint8)
    overlay = draw_mesh_over(image, template.vertices, template.faces, neck_faces, K, w2c, scale)

    pixels, _ = project(template.vertices, K, w2c)
    area = np.zeros((size * scale, size * scale), np.uint8)
    for face in pixels[template.faces]:
        cv2.fillConvexPoly(area, np.round((face + 0.5) * scale).astype(np.int32), 1)
    painted = (overlay != 128).any(axis=-1)
    assert area.sum() > 0.2 * area.size  # the head fills the crop, as in ingest
    assert painted[area > 0].mean() < 0.25
    assert painted[area > 0].mean() > 0.005  # the outline is there
