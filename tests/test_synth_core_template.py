"""The procedural template head and subjects: closed mesh, UVs, neck mask, OBJ I/O, seeded identities."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from relightanyone.synth.presets import get_preset
from relightanyone.synth.subject import make_subject
from relightanyone.synth.template import make_template, read_obj, write_obj, write_template


@pytest.fixture(scope="module")
def demo_template():
    return make_template(get_preset("demo").template_segments)


def test_template_is_a_closed_outward_surface_of_a_few_thousand_vertices(demo_template):
    t = demo_template
    mesh = trimesh.Trimesh(t.vertices, t.faces, process=False)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert 2000 <= len(t.vertices) <= 8000
    assert t.faces.dtype == np.int64 and t.face_uvs.shape == t.faces.shape


def test_template_is_in_canonical_head_space(demo_template):
    t = demo_template
    lm = {name: t.vertices[i] for name, i in t.landmarks.items()}
    assert set(lm) >= {"nose_tip", "chin", "left_ear", "right_ear", "head_top"}
    assert 0.20 <= lm["head_top"][1] - lm["chin"][1] <= 0.28  # chin to crown ~0.24 m
    assert lm["nose_tip"][2] > 0.1 and abs(lm["nose_tip"][0]) < 0.01  # +z out of the face
    assert lm["left_ear"][0] > 0.07 and lm["right_ear"][0] < -0.07
    assert np.linalg.norm(t.vertices.mean(axis=0)) < 0.05  # origin near the head centre


def test_uvs_and_neck_mask(demo_template):
    t = demo_template
    assert t.uvs.min() >= 0.0 and t.uvs.max() <= 1.0
    assert t.face_uvs.max() < len(t.uvs)
    chin_y = t.vertices[t.landmarks["chin"], 1]
    assert t.neck_mask.any() and not t.neck_mask.all()
    assert t.vertices[t.neck_mask, 1].max() < chin_y  # the whole neck is below the jaw
    assert t.vertices[t.neck_mask, 1].min() < -0.18  # and reaches down to the stub's end
    # The front of the face faces +z in UV terms too: the nose tip sits at u ~ 0.5.
    nose_faces = np.nonzero((t.faces == t.landmarks["nose_tip"]).any(axis=1))[0]
    corner = t.face_uvs[nose_faces][t.faces[nose_faces] == t.landmarks["nose_tip"]]
    assert np.allclose(t.uvs[corner, 0], 0.5, atol=0.02)


def test_obj_round_trip_and_template_folder(tmp_path):
    t = make_template(24)
    write_obj(tmp_path / "head.obj", t.vertices, t.faces, t.uvs, t.face_uvs)
    v, f, uv, fuv = read_obj(tmp_path / "head.obj")
    np.testing.assert_allclose(v, t.vertices, atol=1e-8)
    np.testing.assert_array_equal(f, t.faces)
    np.testing.assert_allclose(uv, t.uvs, atol=1e-8)
    np.testing.assert_array_equal(fuv, t.face_uvs)
    write_obj(tmp_path / "plain.obj", t.vertices, t.faces)
    _, f2, uv2, fuv2 = read_obj(tmp_path / "plain.obj")
    assert uv2 is None and fuv2 is None and np.array_equal(f2, t.faces)

    write_template(tmp_path / "template", t)
    mask = np.loadtxt(tmp_path / "template" / "neck_mask.txt", dtype=int).astype(bool)
    np.testing.assert_array_equal(mask, t.neck_mask)
    assert json.loads((tmp_path / "template" / "landmarks.json").read_text()) == t.landmarks


def test_bad_obj_names_the_file(tmp_path):
    bad = tmp_path / "quad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    with pytest.raises(ValueError, match="quad.obj"):
        read_obj(bad)


def test_subjects_are_seed_determined_and_differ():
    t = make_template(32)
    a = make_subject(t, "001", 11, 32)
    a_again = make_subject(t, "001", 11, 32)
    b = make_subject(t, "002", 12, 32)
    for field in ("vertices", "albedo", "specular_intensity", "roughness"):
        np.testing.assert_array_equal(getattr(a, field), getattr(a_again, field))
    assert np.abs(a.vertices - b.vertices).max() > 2e-3  # metres
    assert np.abs(a.albedo - b.albedo).mean() > 0.01
    assert a.albedo.shape == (32, 32, 3) and a.albedo.dtype == np.float32
    assert 0.0 <= a.albedo.min() and a.albedo.max() <= 1.0
    assert a.roughness.min() > 0 and a.roughness.max() <= 1.0 and a.specular_intensity.min() >= 0
    # Shape changes are smooth and modest: still a closed head of about the same size.
    mesh = trimesh.Trimesh(b.vertices, t.faces, process=False)
    assert mesh.is_watertight and 0.6 < mesh.volume / trimesh.Trimesh(t.vertices, t.faces).volume < 1.5
    # The hair cap is darker than the cheeks.
    s = a.albedo.shape[0]
    crown = a.albedo[: s // 10].mean()
    cheek = a.albedo[int(s * 0.55), int(s * 0.6)].mean()
    assert crown < cheek
