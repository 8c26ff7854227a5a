"""The template cache, which ingest's pool workers keep across ingests, follows the file it was read from."""

from __future__ import annotations

import os

import numpy as np

from relightanyone.ingest.tracking import load_template
from relightanyone.synth.template import make_template, write_obj, write_template


def test_cached_template_is_reread_when_the_file_changes(tmp_path):
    template = make_template(12)
    write_template(tmp_path, template)
    first = load_template(tmp_path / "template.obj")
    assert load_template(tmp_path / "template.obj") is first  # cached while unchanged
    moved = template.vertices + np.array([0.0, 0.01, 0.0])
    write_obj(tmp_path / "template.obj", moved, template.faces, template.uvs, template.face_uvs)
    os.utime(tmp_path / "template.obj", ns=(1, 1))  # a different signature even within one clock tick
    second = load_template(tmp_path / "template.obj")
    assert np.allclose(second.vertices, moved, atol=1e-8)
    (tmp_path / "neck_mask.txt").write_text("\n".join("0" for _ in moved) + "\n")
    os.utime(tmp_path / "neck_mask.txt", ns=(2, 2))
    assert not load_template(tmp_path / "template.obj").neck_vertices.any()
