"""Convention checks before any row is written: the mistakes users make with cameras, units and images,
each stopped or its views quarantined with a message naming the cause; clean captures pass silently.

The mutated captures are :mod:`helpers.checks_capture`'s (a custom capture whose images show the head);
the clean captures of the four dataset layouts are a reduced synthetic world. Every command goes through
the top-level ``relightanyone`` command and its error boundary. The image checks (silhouette, colour
order) are tested in ``test_ingest_image_check.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.checks_capture import ingest_custom, make_rendered_capture, other_pose_mesh, quarantine, run
from helpers.small_worlds import make_world, reduced_preset

from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest.checks import (
    CameraCase,
    camera_findings,
    camera_problem,
    explain_cameras,
    surround_findings,
)
from relightanyone.render.mesh import read_obj
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.presets import DatasetSize
from relightanyone.synth.template import make_template, write_obj

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def capture(tmp_path) -> Path:
    return make_rendered_capture(tmp_path / "capture")


# ------------------------------------------------------------------------------------------- mutations
def edit_cameras(root: Path, change) -> None:
    """Apply ``change(K, w2c, width, height) -> (K, w2c)`` to every camera of ``cameras.json``."""
    path = root / "cameras.json"
    document = json.loads(path.read_text())
    for camera in document["cameras"].values():
        K, w2c = change(np.array(camera["K"]), np.array(camera["w2c"]), camera["width"], camera["height"])
        camera["K"], camera["w2c"] = K.tolist(), w2c.tolist()
    path.write_text(json.dumps(document))


def scale_obj(path: Path, factor: float) -> None:
    vertices, faces = read_obj(path)
    write_obj(path, vertices * factor, faces)


def meshes_in_mm(root: Path) -> None:
    """Meshes and template written in millimetres, the capture still declared in metres."""
    for path in (root / "meshes").rglob("*.obj"):
        scale_obj(path, 1000.0)
    scale_obj(root / "template.obj", 1000.0)


def capture_in_mm(root: Path) -> None:
    """Camera translations and meshes in millimetres, declared metres (the template stays in metres)."""
    for path in (root / "meshes").rglob("*.obj"):
        scale_obj(path, 1000.0)

    def to_mm(K, w2c, width, height):
        w2c = w2c.copy()
        w2c[:3, 3] *= 1000.0
        return K, w2c

    edit_cameras(root, to_mm)


def camera_to_world(root: Path) -> None:
    edit_cameras(root, lambda K, w2c, w, h: (K, np.linalg.inv(w2c)))


def opengl_axes(root: Path) -> None:
    edit_cameras(root, lambda K, w2c, w, h: (K, np.diag([1.0, -1.0, -1.0, 1.0]) @ w2c))


def full_sensor_K(root: Path) -> None:
    """K of a sensor 4x the size of the image files."""

    def sensor(K, w2c, width, height):
        K = K.copy()
        K[:2, :2] *= 4
        K[:2, 2] = (K[:2, 2] + 0.5) * 4 - 0.5
        return K, w2c

    edit_cameras(root, sensor)


def principal_point_offset(root: Path) -> None:
    def offset(K, w2c, width, height):
        K = K.copy()
        K[0, 2] -= (width - 1) / 2
        K[1, 2] -= (height - 1) / 2
        return K, w2c

    edit_cameras(root, offset)


def transposed_rotation(root: Path) -> None:
    def transpose(K, w2c, width, height):
        w2c = w2c.copy()
        w2c[:3, :3] = w2c[:3, :3].T
        return K, w2c

    edit_cameras(root, transpose)


DATASET_MISTAKES = {
    # mutation -> (the check that stops it, words the finding must hold)
    "meshes-mm": (meshes_in_mm, "head-size", ["1000x larger than the rig", "in mm"]),
    "capture-mm": (capture_in_mm, "head-size", ["whole capture looks like mm"]),
    "c2w": (camera_to_world, "facing", ["camera-to-world", "invert them"]),
    "opengl": (opengl_axes, "in-front", ["OpenGL camera axes", "flip the cameras' y and z"]),
    "full-sensor-K": (full_sensor_K, "principal-point", ["K fits an image 4x larger", "for 96x128 images"]),
    "pp-offset": (principal_point_offset, "principal-point", ["offsets from the image centre"]),
    "transposed": (transposed_rotation, "facing", ["rotations look transposed"]),
}


def test_clean_capture_passes_every_check_silently(capture, tmp_path):
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert "convention checks: all passed" in result.output
    assert "check " not in result.output.replace("convention checks", "")
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15


@pytest.mark.parametrize("mistake", sorted(DATASET_MISTAKES))
def test_dataset_level_mistake_stops_before_writing_naming_the_cause(capture, tmp_path, mistake):
    mutate, check, words = DATASET_MISTAKES[mistake]
    mutate(capture)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 1, result.output
    finding = next(line for line in result.output.splitlines() if line.strip().startswith(f"check {check}:"))
    for word in words:
        assert word in finding
    assert f"--accept-check {check}" in finding
    assert "nothing written" in result.output.splitlines()[-1]
    assert not (tmp_path / "out" / "custom").exists()


def test_one_camera_given_camera_to_world_is_quarantined_naming_the_cause(capture, tmp_path):
    path = capture / "cameras.json"
    document = json.loads(path.read_text())
    document["cameras"]["c3"]["w2c"] = np.linalg.inv(np.array(document["cameras"]["c3"]["w2c"])).tolist()
    path.write_text(json.dumps(document))
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = quarantine(tmp_path / "out")
    assert {e["item"] for e in refused} == {f"s1/00000{f}/c3/full" for f in range(3)}
    assert all("camera-to-world" in e["reason"] and e["stage"] == "check" for e in refused)
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 12


def test_accepted_check_is_not_applied_and_is_recorded_in_the_manifest(capture, tmp_path):
    other_pose_mesh(capture)
    result = ingest_custom(capture, tmp_path / "out", "--accept-check", "silhouette")
    assert result.exit_code == 0, result.output
    assert "not applied: silhouette" in result.output
    assert quarantine(tmp_path / "out") == []
    manifest = json.loads((tmp_path / "out" / "custom" / "manifest.json").read_text())
    assert manifest["accepted_checks"] == ["silhouette"]
    assert NormalizedDataset(tmp_path / "out" / "custom").manifest.info.accepted_checks == ("silhouette",)


def test_unknown_check_name_is_refused(capture, tmp_path):
    result = ingest_custom(capture, tmp_path / "out", "--accept-check", "everything")
    assert result.exit_code == 1 and "unknown check everything" in result.output


def test_dry_run_and_doctor_run_the_checks_and_write_nothing(capture, tmp_path):
    camera_to_world(capture)
    for command in (
        ["ingest", "custom", capture, "--out", tmp_path / "out", "--dry-run"],
        ["doctor", "custom", capture],
    ):
        result = run(*command)
        assert result.exit_code == 1, result.output
        assert "camera-to-world matrices" in result.output
    assert not (tmp_path / "out").exists()


def test_doctor_lists_view_findings(capture, tmp_path):
    path = capture / "images" / "s1" / "000002" / "c1.png"
    cv2.imwrite(str(path), cv2.imread(str(path))[::-1])
    result = run("doctor", "custom", capture)
    assert result.exit_code == 1, result.output  # any finding fails the doctor
    assert "camera c1 is flipped vertically relative to its mask" in result.output
    assert "doctor: nothing written" in result.output


# ------------------------------------------------------------------------------------ pure functions
def test_camera_problem_names_each_check_in_order():
    K = np.array([[200.0, 0, 47.5], [0, 200.0, 63.5], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[2, 3] = 1.0
    head = np.random.default_rng(0).normal(0, 0.05, (50, 3))
    assert camera_problem(K, w2c, 96, 128, head) is None
    mirrored = w2c @ np.diag([-1.0, 1, 1, 1])
    assert camera_problem(K, mirrored, 96, 128, head).startswith("rotation:")
    assert camera_problem(K * [[1, 1, 4], [1, 1, 4], [1, 1, 1]], w2c, 96, 128, head).startswith(
        "principal-point:"
    )
    assert camera_problem(K, np.diag([1.0, -1, -1, 1]) @ w2c, 96, 128, head).startswith("in-front:")
    far = w2c.copy()
    far[0, 3] = 2.0
    assert camera_problem(K, far, 96, 128, head).startswith("facing:")
    assert camera_problem(K * [[20, 1, 1], [1, 20, 1], [1, 1, 1]], w2c, 96, 128, head).startswith(
        "projection:"
    )


def test_k_scale_is_read_from_the_principal_points_not_only_from_what_fits():
    """Several factors may put the head inside the image; the one that centres the principal points wins."""
    head = np.random.default_rng(1).normal(0, 0.02, (50, 3))
    cases = []
    for k in range(6):
        w2c = np.eye(4)
        w2c[:3, 3] = [0.01 * k, 0.0, 1.0]
        sensor = np.array(
            [[800.0 * 8, 0, (47.5 + 3 + 0.5) * 8 - 0.5], [0, 800.0 * 8, (63.5 + 0.5) * 8 - 0.5], [0, 0, 1]]
        )
        cases.append(CameraCase((f"v{k}",), f"c{k}", sensor, w2c, 96, 128, head))
    assert "8x larger" in explain_cameras(cases)


# --------------------------------------------------------------------------- clean dataset layouts
CLEAN = reduced_preset(
    d1=DatasetSize(train_subjects=1, test_subjects=0, cameras=4, image_size=(64, 96), lights=6),
    d2=DatasetSize(train_subjects=1, test_subjects=0, cameras=4, image_size=(52, 80), frames=2, lights=4),
    d3=DatasetSize(train_subjects=1, test_subjects=0, cameras=8, image_size=(80, 60), lights=4),
    d4=DatasetSize(train_subjects=1, test_subjects=0, cameras=4, image_size=(64, 96), frames=2, lights=4),
)
LAYOUTS = {
    "d1": ("faceolat", "faceolat"),
    "d2": ("ava256", "ava256"),
    "d3": ("stereo-rig", "stereo_rig"),
    "d4": ("nersemble", "nersemble"),
}


@pytest.fixture(scope="module")
def clean_world(tmp_path_factory) -> Path:
    return make_world(tmp_path_factory.mktemp("checks_world"), CLEAN, seed=7, datasets=tuple(LAYOUTS))


@pytest.mark.parametrize("dataset", sorted(LAYOUTS))
def test_clean_dataset_layouts_raise_nothing(clean_world, dataset):
    command, folder = LAYOUTS[dataset]
    result = run(
        "doctor",
        command,
        clean_world / folder,
        "--tracking",
        clean_world / "tracking" / dataset,
        "--template",
        clean_world / "answers" / "template" / "template.obj",
    )
    assert "convention checks: all passed" in result.output, result.output
    # The worlds carry a few faulty inputs on purpose (a camera without its archive, charts too small to
    # detect): doctor fails on those alone, listing them.
    refused = "items refused while planning or aligning" in result.output
    assert result.exit_code == (1 if refused else 0), result.output


# ------------------------------------------------------------------------------ the real Ava-256 rig
def real_rig_cases(real_fixtures: Path, change=None) -> list[CameraCase]:
    """The 80 cameras of the real Ava-256 calibration at the 4TB release's 667x1024, around a template head
    at the point every camera centres on; ``change(K, w2c, width, height)`` mutates each camera."""
    from relightanyone.ingest.calibration import read_krt_json

    cams = read_krt_json(real_fixtures / "ava-256" / "full_rig_6933dab" / "camera_calibration.json")
    cams = cams.resize((667, 1024))
    head = make_template(12).vertices
    rays = []
    for k in range(len(cams)):
        w2c = cams.w2c[k].numpy().astype(np.float64)
        rays.append((-w2c[:3, :3].T @ w2c[:3, 3], w2c[2, :3]))
    projectors = [np.eye(3) - np.outer(d, d) for _, d in rays]
    centre = np.linalg.solve(sum(projectors), sum(p @ o for p, (o, _) in zip(projectors, rays, strict=True)))
    cases = []
    for k, name in enumerate(cams.names):
        K, w2c = cams.K[k].numpy().astype(np.float64), cams.w2c[k].numpy().astype(np.float64)
        if change is not None:
            K, w2c = change(K, w2c, 667, 1024)
        cases.append(CameraCase((f"s/000000/{name}/full",), name, K, w2c, 667, 1024, head + centre))
    return cases


def test_real_rig_passes_and_its_mistakes_are_named(real_fixtures):
    clean = real_rig_cases(real_fixtures)
    assert surround_findings(clean, "s", ()) == [] and camera_findings(clean, "s", ()) == []

    def inverted(K, w2c, width, height):
        return K, np.linalg.inv(w2c)

    def sensor(K, w2c, width, height):
        K = K.copy()
        K[:2, :2] *= 4
        K[:2, 2] = (K[:2, 2] + 0.5) * 4 - 0.5
        return K, w2c

    def opengl(K, w2c, width, height):
        return K, np.diag([1.0, -1.0, -1.0, 1.0]) @ w2c

    expected = {
        # Only 7 cameras fail by geometry here (the others still see the head); the image check quarantines
        # the rest of the views, whose images disagree with their masks.
        inverted: ("projection", "camera-to-world matrices"),
        sensor: (
            "principal-point",
            "K fits an image 4x larger: principal points at (1.5k, 1.7k) px for 667x1024",
        ),
        opengl: ("in-front", "OpenGL camera axes"),
    }
    for change, (check, words) in expected.items():
        cases = real_rig_cases(real_fixtures, change)
        [finding] = surround_findings(cases, "s", ()) or camera_findings(cases, "s", ())
        assert finding.check == check and words in finding.message, finding.message


def test_cameras_that_do_not_surround_the_head_name_the_convention():
    """A rig aimed at the world's origin, where the head is: read as world-to-camera, camera-to-world
    matrices put every camera at one point, still facing the head."""
    head = make_template(12).vertices
    K = np.array([[300.0, 0, 47.5], [0, 300.0, 63.5], [0, 0, 1]])
    cases = []
    for k, azimuth in enumerate(np.radians([-60, -30, 0, 30, 60])):
        w2c = look_at_w2c(np.array([np.sin(azimuth), 0.1, np.cos(azimuth)]), np.zeros(3))
        cases.append(CameraCase((f"v{k}",), f"c{k}", K, np.linalg.inv(w2c), 96, 128, head))
    [finding] = surround_findings(cases, "s", ())
    assert finding.scope == "dataset" and "camera-to-world matrices" in finding.message, finding.message


# ------------------------------------------------------------------------- selections and the lens
def test_selections_that_match_nothing_and_duplicate_cameras_are_named(capture, tmp_path):
    result = ingest_custom(capture, tmp_path / "out", "--cameras", "c1,nosuch", "--dry-run")
    assert result.exit_code == 1
    assert "--cameras: nosuch not in the capture (it has c0, c1, c2, c3, c4)" in result.output
    result = ingest_custom(capture, tmp_path / "out", "--frames", "7", "--dry-run")
    assert (
        result.exit_code == 1
        and "no view was found (check --subjects, --cameras and --frames" in result.output
    )
    path = capture / "cameras.json"
    text = path.read_text()
    path.write_text(text.replace('"cameras": {', '"cameras": {"c1": {}, ', 1))
    result = ingest_custom(capture, tmp_path / "out", "--dry-run")
    assert result.exit_code == 1 and "key 'c1' appears twice" in result.output and str(path) in result.output


def test_distortion_coefficients_out_of_order_stop_the_ingest(capture, tmp_path):
    """k2 and k3 written into the tangential slots on every camera; one odd camera alone passes."""
    path = capture / "cameras.json"
    document = json.loads(path.read_text())
    cameras = document["cameras"]
    cameras["c2"]["dist"] = [0.1, 0.0, 0.12, 0.0, 0.0]
    path.write_text(json.dumps(document))
    alone = run("doctor", "custom", capture)
    assert "check lens" not in alone.output, alone.output
    for camera in cameras.values():
        camera["dist"] = [-0.3, 0.0, 0.12, -0.02, 0.0]
    path.write_text(json.dumps(document))
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 1 and not (tmp_path / "out" / "custom").exists()
    finding = next(line for line in result.output.splitlines() if "check lens" in line)
    assert "p1 = 0.12, p2 = -0.02" in finding and "OpenCV's order k1 k2 p1 p2 k3" in finding
    assert "--accept-check lens" in finding
