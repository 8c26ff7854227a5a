"""OBJ loading with UV seams, face and vertex normals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relightanyone.render.mesh import TexturedMesh, face_normals, load_obj, vertex_normals

# Two triangles sharing the edge (0, 2); vertex 2 sits on a UV seam (two texture coordinates).
SEAM_OBJ = """v 0 0 0
v 1 0 0
v 0 1 0
v -1 0 0
vt 0.1 0.1
vt 0.4 0.1
vt 0.1 0.4
vt 0.6 0.1
vt 0.9 0.4
vt 0.6 0.4
f 1/1 2/2 3/3
f 1/4 3/5 4/6
"""


def test_load_obj_keeps_topology_and_seams(tmp_path):
    path = tmp_path / "seam.obj"
    path.write_text(SEAM_OBJ)
    mesh = load_obj(path)
    assert mesh.vertices.shape == (4, 3) and mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    corner_uvs = mesh.uvs[mesh.face_uvs]
    np.testing.assert_allclose(corner_uvs[0], [[0.1, 0.1], [0.4, 0.1], [0.1, 0.4]])
    np.testing.assert_allclose(corner_uvs[1], [[0.6, 0.1], [0.9, 0.4], [0.6, 0.4]])
    # Vertex 0 and 2 appear in both faces with different UVs: the seam is kept, the 3D vertex is shared.
    assert mesh.face_uvs[0, 0] != mesh.face_uvs[1, 0]


def test_load_obj_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        load_obj(tmp_path / "missing.obj")
    bare = tmp_path / "bare.obj"
    bare.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="bare.obj: no texture coordinates"):
        load_obj(bare)
    with pytest.raises(ValueError, match="faces index vertices outside"):
        TexturedMesh(np.zeros((2, 3)), np.array([[0, 1, 2]]), np.zeros((3, 2)), np.array([[0, 1, 2]]))


def test_load_real_ava256_topology(real_fixtures):
    mesh = load_obj(real_fixtures / "ava-256" / "face_topology.obj")
    assert mesh.vertices.shape == (7306, 3)
    assert mesh.faces.shape == (11432, 3) and mesh.face_uvs.shape == (11432, 3)
    assert len(np.unique(mesh.face_uvs)) == 5779
    assert mesh.uvs.min() >= 0.0 and mesh.uvs.max() <= 1.0
    # 38 vertices lie on UV seams (two texture coordinates each), as counted from the file's f records.
    pairs = np.unique(np.stack([mesh.faces.ravel(), mesh.face_uvs.ravel()], -1), axis=0)
    _, uv_per_vertex = np.unique(pairs[:, 0], return_counts=True)
    assert (uv_per_vertex == 2).sum() == 38 and uv_per_vertex.max() == 2
    # First vertex as written in the file (millimetres).
    np.testing.assert_allclose(mesh.vertices[0], [9.24196399809, 76.0411107614, 1129.07910921])


def test_vertex_normals_of_a_sphere_point_outwards():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    vertices = torch.tensor(sphere.vertices, dtype=torch.float64)[None].repeat(2, 1, 1)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    normals = vertex_normals(vertices, faces)
    radial = vertices / vertices.norm(dim=-1, keepdim=True)
    assert normals.shape == (2, len(sphere.vertices), 3)
    assert ((normals * radial).sum(-1) > 0.995).all()
    unit_faces = face_normals(vertices[0], faces)
    centres = vertices[0][faces].mean(1)
    assert ((unit_faces * centres).sum(-1) > 0).all()
    torch.testing.assert_close(unit_faces.norm(dim=-1), torch.ones(len(faces), dtype=torch.float64))


def test_vertex_normals_weight_by_area_and_are_differentiable():
    # A large face along +z and a sliver tilted face share vertex 0: the large one dominates.
    vertices = torch.tensor(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.01], [0.01, 0, 0]],
        dtype=torch.float64,
        requires_grad=True,
    )
    faces = torch.tensor([[0, 1, 2], [0, 3, 4]])
    normals = vertex_normals(vertices[None], faces)[0]
    assert normals[0, 2] > 0.99
    assert normals[3].norm().item() == pytest.approx(1.0)
    normals[0].sum().backward()
    assert torch.isfinite(vertices.grad).all()
