"""Ground-truth ray tracer: light additivity, analytic Lambert, projection with distortion, shadows."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.raytrace import (
    PointLights,
    Scene,
    SynthCamera,
    render,
    sample_texture,
    textured_quad,
)
from relightanyone.synth.subject import make_subject
from relightanyone.synth.template import make_template


def look_at_camera(centre, target, width, height, f, dist=None, name="cam") -> SynthCamera:
    w2c = look_at_w2c(centre, target)
    K = np.array([[f, 0, width / 2 - 0.5], [0, f, height / 2 - 0.5], [0, 0, 1.0]])
    return SynthCamera(name, K, w2c, width, height, np.zeros(5) if dist is None else np.asarray(dist, float))


def constant_scene(mesh: trimesh.Trimesh, albedo=(0.5, 0.5, 0.5), specular=0.0, roughness=0.5) -> Scene:
    faces = np.asarray(mesh.faces, dtype=np.int64)
    return Scene(
        np.asarray(mesh.vertices, float),
        faces,
        np.full((1, 2), 0.5),
        np.zeros_like(faces),
        np.asarray(albedo, np.float32).reshape(1, 1, 3),
        np.full((1, 1), specular, np.float32),
        np.full((1, 1), roughness, np.float32),
    )


@pytest.fixture(scope="module")
def head():
    template = make_template(40)
    subject = make_subject(template, "001", 3, 64)
    return template, subject, Scene.from_subject(template, subject)


def test_full_on_equals_sum_of_olat(head):
    _, _, scene = head
    cam = look_at_camera(
        [0.3, 0.1, 1.2], [0, -0.02, 0], 64, 96, 96 * 1.25 / 0.4, dist=[0.1, -0.3, 1e-3, -1e-3, 0.5]
    )
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(7, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lights = PointLights(1.5 * dirs, rng.uniform(0.5, 3.0, size=(7, 3)))
    olat = render(scene, cam, lights, per_light=True)
    full = render(scene, cam, lights)
    assert olat.image.shape == (7, 96, 64, 3) and full.image.shape == (96, 64, 3)
    np.testing.assert_allclose(olat.image.sum(axis=0), full.image, rtol=1e-5, atol=1e-7)
    assert (olat.image > 0).any(axis=(1, 2, 3)).sum() >= 5  # most lights reach the visible side
    assert full.image[full.mask].min() >= 0 and full.image[~full.mask].max() == 0
    # Specular lobe: the same scene without specular is darker, never brighter.
    matte = Scene(
        scene.vertices,
        scene.faces,
        scene.uvs,
        scene.face_uvs,
        scene.albedo,
        np.zeros((1, 1), np.float32),
        scene.roughness,
    )
    matte_image = render(matte, cam, lights).image
    assert (matte_image <= full.image + 1e-6).all() and (full.image - matte_image).max() > 1e-3


def test_sphere_matches_analytic_lambert():
    radius = 0.1
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    albedo = np.array([0.6, 0.4, 0.2])
    scene = constant_scene(sphere, albedo)
    cam = look_at_camera([0, 0, 1.0], [0, 0, 0], 80, 80, 80 * 1.0 / 0.25)
    light_pos = np.array([0.6, 0.8, 1.5])
    intensity = np.array([2.0, 2.0, 2.0])
    result = render(scene, cam, PointLights(light_pos[None], intensity[None]))
    assert 0.35 < result.mask.mean() < 0.65

    origins, directions = cam.pixel_rays(1)
    forward = cam.w2c[2, :3]
    t = result.depth.reshape(-1) / (directions @ forward)
    points = origins + directions * t[:, None]
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    to_light = light_pos - points
    d2 = (to_light**2).sum(axis=1)
    cos = (normals * to_light).sum(axis=1) / np.sqrt(d2)
    expected = albedo / np.pi * intensity * (np.maximum(cos, 0) / d2)[:, None]
    hit = result.mask.reshape(-1) & (cos > 0.2)
    assert hit.sum() > 1000
    np.testing.assert_allclose(result.image.reshape(-1, 3)[hit], expected[hit], rtol=1.5e-2)
    # Depth is the camera z of the surface: the sphere's nearest point is 0.9 m away.
    assert abs(result.depth[result.mask].min() - 0.9) < 2e-3


def test_vertices_project_where_the_renderer_hits_their_triangles(head):
    template, subject, scene = head
    cam = look_at_camera(
        [0.25, 0.05, 1.1], [0, -0.02, 0], 120, 180, 180 * 1.1 / 0.4, dist=[2.5, -20.0, 3e-3, -2e-3, 50.0]
    )
    result = render(scene, cam, PointLights([[0, 0, 2.0]], [[1, 1, 1]]))
    uv = cam.project(subject.vertices)
    cam_z = subject.vertices @ cam.w2c[2, :3] + cam.w2c[2, 3]
    checked = 0
    for index in np.random.default_rng(1).permutation(len(subject.vertices)):
        u, v = np.round(uv[index]).astype(int)
        if not (2 <= u < cam.width - 2 and 2 <= v < cam.height - 2):
            continue
        if abs(result.depth[v, u] - cam_z[index]) > 2e-3:  # hidden behind other surface
            continue
        fan = np.nonzero((template.faces == index).any(axis=1))[0]
        assert result.triangle_id[v, u] in fan, (
            f"vertex {index} at {uv[index]} hit triangle {result.triangle_id[v, u]}"
        )
        checked += 1
        if checked == 60:
            break
    assert checked == 60
    # The distortion is strong enough that ignoring it would move points by more than a pixel.
    undistorted = SynthCamera("u", cam.K, cam.w2c, cam.width, cam.height).project(subject.vertices)
    assert np.abs(undistorted - uv).max() > 1.0


def test_points_behind_an_occluder_are_dark():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    scene = constant_scene(sphere)
    cam = look_at_camera([0, 0, 1.0], [0, 0, 0], 48, 48, 48 * 1.0 / 0.3)
    light = PointLights([[2.0, 0.0, 0.3]], [[5.0, 5.0, 5.0]])
    open_image = render(scene, cam, light).image
    lit = open_image.sum(axis=-1) > 1e-4
    assert lit.sum() > 100
    # A board at x = 0.3 between the light and the sphere, outside the camera's view.
    board = textured_quad(
        [[0.3, 0.5, -0.5], [0.3, 0.5, 0.8], [0.3, -0.5, 0.8], [0.3, -0.5, -0.5]], np.array([0.5, 0.5, 0.5])
    )
    shadowed = render(scene.merge(board), cam, light)
    assert shadowed.mask.sum() == render(scene, cam, light).mask.sum()  # the board is not in view
    assert shadowed.image[lit].max() == 0.0


def test_background_supersampling_and_extra_meshes(head):
    _, _, scene = head
    cam = look_at_camera([0, 0, 1.2], [0, -0.02, 0], 40, 60, 60 * 1.2 / 0.45)
    light = PointLights([[0.5, 0.5, 1.5]], [[2.0, 2.0, 2.0]])
    plate = textured_quad(
        [[-1, 1, -0.4], [1, 1, -0.4], [1, -1, -0.4], [-1, -1, -0.4]], np.array([0.8, 0.8, 0.8])
    )
    with_plate = render(scene.merge(plate), cam, light)
    alone = render(scene, cam, light, background=(0.1, 0.2, 0.3))
    np.testing.assert_array_equal(with_plate.mask, alone.mask)  # mask is the head's silhouette only
    assert (with_plate.triangle_id[~alone.mask] >= len(scene.faces)).all()  # the plate fills the rest
    np.testing.assert_allclose(
        alone.image[~alone.mask], np.broadcast_to([0.1, 0.2, 0.3], alone.image[~alone.mask].shape)
    )
    fine = render(scene, cam, light, supersampling=3)
    assert fine.image.shape == alone.image.shape
    inner = (
        alone.mask
        & np.roll(alone.mask, 2, 0)
        & np.roll(alone.mask, -2, 0)
        & np.roll(alone.mask, 2, 1)
        & np.roll(alone.mask, -2, 1)
    )
    ratio = fine.image[inner].mean() / alone.image[inner].mean()
    assert 0.9 < ratio < 1.1
    with pytest.raises(ValueError, match="per_light"):
        render(scene, cam, light, per_light=True, background=(0, 0, 0))


def test_texture_lookup_orientation():
    texture = np.zeros((2, 2, 3), np.float32)
    texture[0, 1] = 1.0  # top-right texel: u > 0.5, v > 0.5
    values = sample_texture(texture, np.array([[0.75, 0.75], [0.25, 0.25]]))
    np.testing.assert_allclose(values, [[1, 1, 1], [0, 0, 0]])


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="camera bad"):
        SynthCamera("bad", np.eye(2), np.eye(4), 10, 10)
    with pytest.raises(ValueError, match="dist"):
        SynthCamera("bad", np.eye(3), np.eye(4), 10, 10, np.zeros(3))
    with pytest.raises(ValueError, match="intensities"):
        PointLights(np.zeros((2, 3)), np.ones((3, 3)))
    quad = textured_quad(np.eye(4, 3), np.array([0.5, 0.5, 0.5]))
    broken = Scene(
        quad.vertices,
        quad.faces + 5,
        quad.uvs,
        quad.face_uvs,
        quad.albedo,
        quad.specular_intensity,
        quad.roughness,
    )
    with pytest.raises(ValueError, match="vertices"):
        render(
            broken,
            SynthCamera("c", np.eye(3), np.eye(4), 4, 4),
            PointLights(np.zeros((1, 3)), np.ones((1, 3))),
        )
