"""D1 FaceOLAT-like writer on a tiny run: files parse like the real ones and agree with the truth."""

from __future__ import annotations

import dataclasses
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from relightanyone.synth import d1_faceolat
from relightanyone.synth.envmap import read_exr
from relightanyone.synth.presets import DatasetSize, get_preset
from relightanyone.synth.raytrace import Scene, SynthCamera, render
from relightanyone.synth.subject import make_subject
from relightanyone.synth.template import make_template

PRESET = dataclasses.replace(
    get_preset("tiny"),
    template_segments=32,
    texture_size=32,
    d1=DatasetSize(train_subjects=2, test_subjects=1, cameras=3, image_size=(64, 96), lights=7),
)


def generate(out: Path):
    template = make_template(PRESET.template_segments)
    subjects = [make_subject(template, f"{i + 1:03d}", 100 + i, PRESET.texture_size) for i in range(3)]
    splits = {"001": "train", "002": "train", "003": "test"}
    counter = []
    truth = d1_faceolat.generate(
        out, PRESET, template, subjects, splits, np.random.default_rng(9), counter.append
    )
    return template, subjects, truth, counter


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    out = tmp_path_factory.mktemp("d1")
    template, subjects, truth, counter = generate(out)
    return out / "faceolat", template, subjects, truth, counter


def tag_paths(path: Path) -> set[str]:
    paths = set()

    def walk(element, prefix):
        here = f"{prefix}/{element.tag}"
        paths.add(here)
        for child in element:
            walk(child, here)

    walk(ET.parse(path).getroot(), "")
    return paths


def read_metashape(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, int, int]]:
    """What a reader of FaceOLAT's 001.xml does: label -> (K, dist, world_from_camera 4x4, width, height)."""
    chunk = ET.parse(path).getroot().find("chunk")
    t = chunk.find("transform")
    rotation = np.array(t.find("rotation").text.split(), float).reshape(3, 3)
    translation = np.array(t.find("translation").text.split(), float)
    scale = float(t.find("scale").text)
    sensors = {}
    for sensor in chunk.find("sensors"):
        cal = sensor.find("calibration")
        res = cal.find("resolution")
        w, h = int(res.get("width")), int(res.get("height"))
        v = {k: float(cal.find(k).text) for k in ("f", "cx", "cy", "b1", "k1", "k2", "k3", "p1", "p2")}
        K = np.array(
            [[v["f"] + v["b1"], 0, w / 2 + v["cx"] - 0.5], [0, v["f"], h / 2 + v["cy"] - 0.5], [0, 0, 1]]
        )
        dist = np.array([v["k1"], v["k2"], v["p2"], v["p1"], v["k3"]])
        sensors[sensor.get("id")] = (K, dist, w, h)
    cameras = {}
    for camera in chunk.find("cameras"):
        camera_to_chunk = np.array(camera.find("transform").text.split(), float).reshape(4, 4)
        world_from_camera = np.eye(4)
        world_from_camera[:3, :3] = rotation @ camera_to_chunk[:3, :3]
        world_from_camera[:3, 3] = scale * rotation @ camera_to_chunk[:3, 3] + translation
        K, dist, w, h = sensors[camera.get("sensor_id")]
        cameras[camera.get("label")] = (K, dist, world_from_camera, w, h)
    return cameras


def test_light_files_have_the_real_schema(world, real_fixtures):
    root, _, _, truth, _ = world
    real_meta = json.loads((real_fixtures / "faceolat/light_pattern_metadata.json").read_text())
    meta = json.loads((root / "relighting/lights/light_pattern_metadata.json").read_text())
    assert set(meta) == set(real_meta)
    assert set(meta["light_patterns"][0]) == set(real_meta["light_patterns"][0])
    assert [p["name"] for p in meta["light_patterns"]] == ["full"] + [f"OLAT_{i:03d}" for i in range(7)]
    assert meta["light_patterns"][0]["light_index_durations"] == [[i, 0.35] for i in range(7)]
    assert meta["light_patterns"][4]["light_index_durations"] == [[3, 7]]
    positions = np.array(meta["light_positions"])
    assert positions.shape == (7, 3)
    world_from_canonical = truth.world_from_canonical
    expected = truth.light_positions @ world_from_canonical[:3, :3].T + world_from_canonical[:3, 3]
    np.testing.assert_allclose(positions, 1000.0 * expected, rtol=1e-12)
    assert np.linalg.norm(positions.mean(axis=0) - [606, 1551, 536]) < 400  # mm, like the real rig

    real_schedule = json.loads((real_fixtures / "faceolat/light_pattern_per_frame.json").read_text())
    nominal = json.loads((root / "relighting/lights/light_pattern_per_frame.json").read_text())
    assert type(nominal[0]) is type(real_schedule[0]) and len(nominal[0]) == 2
    takes = {
        s: json.loads((root / f"{s}/lights/ID20{s}/light_pattern_per_frame.json").read_text())
        for s in ("001", "002")
    }
    assert takes["001"] == nominal
    assert len(takes["002"]) == len(nominal) + 1  # one take has an extra full-on frame
    for schedule in takes.values():
        assert [f for f, _ in schedule] == list(range(len(schedule)))
        assert sorted(p for _, p in schedule if p) == list(range(1, 8))  # each OLAT exactly once
        assert schedule[0][1] == 0 and schedule[-1][1] == 0
    assert truth.extra["full_on_frames"]["002"][:2] == [0, 1]


def test_xml_matches_the_real_structure_and_projects_like_the_renderer(world, real_fixtures):
    root, template, subjects, truth, _ = world
    assert tag_paths(root / "calibration/cameras/001.xml") == tag_paths(real_fixtures / "faceolat/001.xml")
    subject = subjects[1]
    pose = truth.head_poses[("002", 0)]
    scene = Scene.from_subject(template, subject, head_pose=pose)
    canonical = subject.vertices @ pose[:3, :3].T + pose[:3, 3]
    W = truth.world_from_canonical
    world_points = canonical @ W[:3, :3].T + W[:3, 3]
    cameras = read_metashape(root / "calibration/cameras/002.xml")
    assert sorted(cameras) == ["Cam01", "Cam02", "Cam03"]
    for name, (K, dist, world_from_camera, w, h) in cameras.items():
        assert (w, h) == (64, 96)
        w2c = np.linalg.inv(world_from_camera)
        rvec, _ = cv2.Rodrigues(w2c[:3, :3])
        uv, _ = cv2.projectPoints(world_points.reshape(-1, 1, 3), rvec, w2c[:3, 3], K, dist)
        uv = uv.reshape(-1, 2)
        t = truth.cameras[name]
        result = render(
            scene, SynthCamera(name, t.K, t.w2c, t.width, t.height, t.dist), d1_faceolat.d1_rig_lights(PRESET)
        )
        cam_z = canonical @ t.w2c[2, :3] + t.w2c[2, 3]
        checked = 0
        for index in range(len(canonical)):
            u, v = np.round(uv[index]).astype(int)
            if not (0 <= u < w and 0 <= v < h) or abs(result.depth[v, u] - cam_z[index]) > 3e-3:
                continue
            fan = np.nonzero((template.faces == index).any(axis=1))[0]
            # Within 1 px: the pixel at the projection, or one of its neighbours, shows the vertex's triangles.
            window = result.triangle_id[max(v - 1, 0) : v + 2, max(u - 1, 0) : u + 2]
            assert np.isin(window, fan).any(), f"{name}: vertex {index} projects to {uv[index]}"
            checked += 1
        assert checked > 20


def test_frames_are_colour_encoded_radiance(world, real_fixtures):
    root, template, subjects, truth, counter = world
    assert sum(counter) == 3 * 3  # one progress step per (subject, camera)
    text = (root / "color-calibration/colorcalib_exr.mat").read_text()
    real_text = (real_fixtures / "faceolat/colorcalib_exr.mat").read_text()
    assert len(text.split("\n")) == len(real_text.split("\n")) == 4
    assert all(line.endswith(" ") for line in text.split("\n")) and not text.endswith("\n")
    matrix = np.array([line.split() for line in text.split("\n")], float)
    assert np.array_equal(matrix[3], [0, 0, 0, 1]) and np.array_equal(matrix[:3, 3], [0, 0, 0])

    schedule = json.loads((root / "001/lights/ID20001/light_pattern_per_frame.json").read_text())
    folder = root / "001/OutputEXR/Cam02/ID20001"
    assert len(list(folder.glob("ID20001.*.exr"))) == len(schedule)
    frames = {p: read_exr(folder / f"ID20001.{f:06d}.exr") for f, p in schedule}
    pose = truth.head_poses[("001", 0)]
    t = truth.cameras["Cam02"]
    olat = render(
        Scene.from_subject(template, subjects[0], head_pose=pose),
        SynthCamera("Cam02", t.K, t.w2c, t.width, t.height, t.dist),
        d1_faceolat.d1_rig_lights(PRESET),
        per_light=True,
    ).image
    for pattern in range(1, 8):
        recovered = frames[pattern] @ matrix[:3, :3].T  # FaceOLAT: M @ (rgb - black), black = 0
        np.testing.assert_allclose(recovered, olat[pattern - 1], rtol=4e-3, atol=2e-4)
    assert max(olat[k].max() for k in range(7)) > 0.02  # the lights reach the face
    full = sum(frames[p] for p in range(1, 8)) * truth.extra["full_on_scale"]
    np.testing.assert_allclose(frames[0], full, rtol=4e-3, atol=1e-4)
    np.testing.assert_allclose(truth.colour_response["Cam02"], np.linalg.inv(matrix[:3, :3]), rtol=1e-6)


def test_mapping_and_determinism(world, real_fixtures, tmp_path):
    root, _, _, truth, _ = world
    real = json.loads((real_fixtures / "faceolat/calibration_mapping.json").read_text())
    mapping = json.loads((root / "calibration/calibration_mapping.json").read_text())
    assert set(mapping) == set(real) and set(mapping["summary"]) == set(real["summary"])
    assert set(mapping["calibrations"][0]) == set(real["calibrations"][0])
    assert [c["subject_name"] for c in mapping["calibrations"]] == ["001", "002", "003"]
    assert truth.splits["003"] == "test"
    assert (
        abs(np.cbrt(np.linalg.det(truth.world_from_canonical[:3, :3])) - 1.0) > 0.1
    )  # the world is not metric
    generate(tmp_path)
    again = tmp_path / "faceolat"
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (root / rel).read_bytes() == (again / rel).read_bytes(), rel
