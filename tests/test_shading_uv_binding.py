"""UV binding on a procedural two-chart mesh and on the real Ava-256 face topology."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relightanyone.render.mesh import load_obj
from relightanyone.render.uv_binding import UVBinding, texel_centre_uvs

GRID = 9  # vertices per side of the (s, t) grid
CHART_HEIGHT = 0.35


def _two_chart_surface():
    """Surface P(s, t) = (s, t, 0.2 sin(pi s)) cut at s = 0.5 into two UV charts (the right one mirrored).

    Returns vertices (V, 3), faces (F, 3), uvs (T, 2), face_uvs (F, 3), the (s, t) of each vertex, and the
    affine maps uv -> (s, t) of both charts.
    """
    s, t = np.meshgrid(np.linspace(0, 1, GRID), np.linspace(0, 1, GRID), indexing="ij")
    st = np.stack([s.ravel(), t.ravel()], -1)
    vertices = np.stack([st[:, 0], st[:, 1], 0.2 * np.sin(np.pi * st[:, 0])], -1)
    vid = np.arange(GRID * GRID).reshape(GRID, GRID)
    half = GRID // 2

    def chart_a(point):  # s in [0, 0.5] -> u in [0.05, 0.45]
        return np.array([0.05 + 0.8 * point[0], 0.1 + CHART_HEIGHT * point[1]])

    def chart_b(point):  # s in [0.5, 1] -> u in [0.95, 0.55], mirrored
        return np.array([0.95 - 0.8 * (point[0] - 0.5), 0.55 + CHART_HEIGHT * point[1]])

    uvs, uv_index, faces, face_uvs = [], {}, [], []

    def uv_id(vertex, chart):
        key = (vertex, chart)
        if key not in uv_index:
            uv_index[key] = len(uvs)
            uvs.append((chart_a if chart == 0 else chart_b)(st[vertex]))
        return uv_index[key]

    for i in range(GRID - 1):
        chart = 0 if i < half else 1
        for j in range(GRID - 1):
            a, b, c, d = vid[i, j], vid[i + 1, j], vid[i + 1, j + 1], vid[i, j + 1]
            for tri in ((a, b, c), (a, c, d)):  # counter-clockwise in (s, t): normals towards +z
                faces.append(tri)
                face_uvs.append([uv_id(v, chart) for v in tri])
    return vertices, np.array(faces), np.array(uvs), np.array(face_uvs), st, (chart_a, chart_b)


@pytest.fixture(scope="module")
def surface():
    return _two_chart_surface()


@pytest.fixture(scope="module")
def binding(surface):
    vertices, faces, uvs, face_uvs, *_ = surface
    return UVBinding.from_mesh(vertices, faces, uvs, face_uvs, size=64)


def test_texel_centres_follow_the_image_convention():
    centres = texel_centre_uvs(4)
    assert centres[0, 0].tolist() == pytest.approx([0.125, 0.875])  # top-left texel: small u, large v
    assert centres[3, 2].tolist() == pytest.approx([0.625, 0.125])


def test_maps_and_coverage(binding):
    size = binding.size
    assert binding.face_index.shape == (size, size) and binding.face_index.dtype == torch.int64
    assert binding.barycentrics.shape == (size, size, 3)
    assert torch.equal(binding.valid, binding.face_index >= 0)
    assert (binding.barycentrics[~binding.valid] == 0).all()
    bary = binding.barycentrics[binding.valid]
    assert (bary >= 0).all() and torch.allclose(bary.sum(-1), torch.ones(len(bary)))
    # Two 0.4 x 0.35 charts; boundary texels are within one texel of the chart outline.
    area, perimeter = 2 * 0.4 * CHART_HEIGHT, 2 * 2 * (0.4 + CHART_HEIGHT)
    assert abs(binding.valid.sum().item() - area * size**2) <= 0.5 * perimeter * size
    # Nothing outside the charts: the gap between them and the margins stay invalid.
    centres = texel_centre_uvs(size)
    outside = (centres[..., 0] > 0.46) & (centres[..., 0] < 0.54) | (centres[..., 1] < 0.09)
    assert not binding.valid.numpy()[outside].any()


def test_interpolated_uv_is_the_texel_centre(binding):
    texel_uvs = binding.texel_uvs().numpy()
    centres = texel_centre_uvs(binding.size)
    valid = binding.valid.numpy()
    np.testing.assert_allclose(texel_uvs[valid], centres[valid], atol=1e-6)
    assert (texel_uvs[~valid] == 0).all()


def test_interpolation_recovers_the_surface_parameter(surface, binding):
    """(s, t) is affine in UV on each chart, so interpolating it must invert the chart map exactly."""
    _, _, _, _, st, (chart_a, chart_b) = surface
    values = torch.from_numpy(st).float()[None]  # (1, V, 2)
    image = binding.interpolate(values)[0].permute(1, 2, 0).numpy()  # (S, S, 2)
    centres = texel_centre_uvs(binding.size)
    valid = binding.valid.numpy()
    left = valid & (centres[..., 0] < 0.5)
    right = valid & (centres[..., 0] > 0.5)
    expected_left = np.stack([(centres[..., 0] - 0.05) / 0.8, (centres[..., 1] - 0.1) / CHART_HEIGHT], -1)
    expected_right = np.stack(
        [0.5 + (0.95 - centres[..., 0]) / 0.8, (centres[..., 1] - 0.55) / CHART_HEIGHT], -1
    )
    np.testing.assert_allclose(image[left], expected_left[left], atol=1e-5)
    np.testing.assert_allclose(image[right], expected_right[right], atol=1e-5)
    assert (image[~valid] == 0).all()


def test_interpolation_is_differentiable(surface):
    vertices, faces, uvs, face_uvs, *_ = surface
    small = UVBinding.from_mesh(vertices, faces, uvs, face_uvs, size=8)
    values = torch.randn(1, len(vertices), 1, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(small.interpolate, (values,))


def test_normals_and_tangent_frames(surface, binding):
    vertices, *_ = surface
    batch = torch.from_numpy(vertices).float()[None].repeat(2, 1, 1)
    normals = binding.interpolate_normals(batch)
    frames = binding.tangent_frames(batch)
    assert normals.shape == (2, 3, 64, 64) and frames.shape == (2, 3, 3, 64, 64)
    valid = binding.valid
    n = normals[0].permute(1, 2, 0)[valid]
    positions = binding.interpolate(batch)[0].permute(1, 2, 0)[valid]
    analytic = torch.nn.functional.normalize(
        torch.stack(
            [-0.2 * np.pi * torch.cos(np.pi * positions[:, 0]), torch.zeros(len(n)), torch.ones(len(n))], -1
        ),
        dim=-1,
    )
    assert ((n * analytic).sum(-1) > 0.99).all()  # smooth normals of a coarse mesh, facing +z
    matrices = frames[0].permute(2, 3, 0, 1)[valid]  # (P, 3, 3)
    eye = torch.eye(3).expand_as(matrices)
    torch.testing.assert_close(matrices.transpose(1, 2) @ matrices, eye, atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(matrices), torch.ones(len(matrices)), atol=1e-5, rtol=0)
    torch.testing.assert_close(matrices[:, :, 2], n, atol=1e-6, rtol=0)
    # The tangent follows increasing u: +s on the left chart, -s on the mirrored right chart.
    u = binding.texel_uvs()[valid][:, 0]
    tangent_x = matrices[:, 0, 0]
    assert (tangent_x[u < 0.5] > 0.5).all() and (tangent_x[u > 0.5] < -0.5).all()
    assert (frames[:, :, :, ~valid] == 0).all()


def test_overlapping_charts_resolve_to_the_lowest_face():
    uvs = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9]])
    vertices = np.random.default_rng(0).normal(size=(6, 3))
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    face_uvs = np.array([[0, 1, 2], [0, 1, 2]])  # the same UV triangle twice
    binding = UVBinding.from_mesh(vertices, faces, uvs, face_uvs, size=16)
    assert set(binding.face_index[binding.valid].tolist()) == {0}


def test_bad_input_is_rejected(surface):
    vertices, faces, uvs, face_uvs, *_ = surface
    with pytest.raises(ValueError, match="face_uvs index texture coordinates"):
        UVBinding.from_mesh(vertices, faces, uvs[:3], face_uvs, size=8)
    binding = UVBinding.from_mesh(vertices, faces, uvs, face_uvs, size=8)
    with pytest.raises(ValueError, match=r"vertex_values must be \(B, 81, C\)"):
        binding.interpolate(torch.zeros(1, 80, 3))


def test_real_ava256_face_topology(real_fixtures):
    mesh = load_obj(real_fixtures / "ava-256" / "face_topology.obj")
    binding = UVBinding.from_mesh(mesh.vertices, mesh.faces, mesh.uvs, mesh.face_uvs, size=128)
    valid = binding.valid.numpy()
    centres = texel_centre_uvs(128)
    np.testing.assert_allclose(binding.texel_uvs().numpy()[valid], centres[valid], atol=1e-6)
    corners = mesh.uvs[mesh.face_uvs]
    edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    uv_area = 0.5 * np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0]).sum()
    assert valid.mean() == pytest.approx(min(uv_area, 1.0), abs=0.01)
    # Every face large enough to contain a texel centre is used; each texel is inside its face's UV box.
    used_faces = binding.face_index[binding.valid]
    face_boxes_lo, face_boxes_hi = corners.min(1), corners.max(1)
    texel_uv = centres[valid]
    assert (texel_uv >= face_boxes_lo[used_faces.numpy()] - 1e-9).all()
    assert (texel_uv <= face_boxes_hi[used_faces.numpy()] + 1e-9).all()
    # Position map in millimetres: interpolated points lie on the mesh's bounding box.
    positions = binding.interpolate(torch.from_numpy(mesh.vertices).float()[None])[0].permute(1, 2, 0).numpy()
    used = mesh.vertices[np.unique(mesh.faces)]
    assert (positions[valid] >= used.min(0) - 1e-3).all() and (positions[valid] <= used.max(0) + 1e-3).all()
