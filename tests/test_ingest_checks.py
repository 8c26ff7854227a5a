"""Convention checks before any row is written: the mistakes users make with cameras, units and images,
each stopped or its views quarantined with a message naming the cause; clean captures pass silently.

The mutated captures are :mod:`helpers.checks_capture`'s (a custom capture whose images show the head);
the clean captures of the four dataset layouts are a reduced synthetic world. Every command goes through
the top-level ``relightanyone`` command and its error boundary.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from helpers.checks_capture import head_pose, make_rendered_capture
from helpers.small_worlds import make_world, reduced_preset

from relightanyone.align.geometry import similarity, transform_points
from relightanyone.cli import cli
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest.checks import (
    CameraCase,
    camera_findings,
    camera_problem,
    explain_cameras,
    subsample,
    surround_findings,
)
from relightanyone.ingest.decode import TaskDecoder
from relightanyone.ingest.image_check import hull_indices, hull_mask, image_foreground
from relightanyone.ingest.image_decisions import mismatched_frames
from relightanyone.render.mesh import read_obj
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.presets import DatasetSize
from relightanyone.synth.template import make_template, write_obj

pytestmark = pytest.mark.usefixtures("one_torch_thread")


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


def run(*args: str):
    return CliRunner().invoke(cli, [str(a) for a in args])


def ingest_custom(capture: Path, out: Path, *extra: str):
    return run("ingest", "custom", capture, "--out", out, "--preset", "tiny", *extra)


def quarantine(out: Path) -> list[dict]:
    path = out / "custom" / "quarantine.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []


@pytest.fixture
def capture(tmp_path) -> Path:
    return make_rendered_capture(tmp_path / "capture")


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


def test_swapped_images_quarantine_both_views_naming_the_pair(capture, tmp_path):
    for frame in ("000000", "000001"):
        folder = capture / "images" / "s1" / frame
        first, second = (folder / "c0.png").read_bytes(), (folder / "c2.png").read_bytes()
        (folder / "c0.png").write_bytes(second)
        (folder / "c2.png").write_bytes(first)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = {entry["item"]: entry["reason"] for entry in quarantine(tmp_path / "out")}
    expected = {f"s1/00000{f}/{c}/full" for f in (0, 1) for c in ("c0", "c2")}
    assert set(refused) == expected
    assert all("cameras c0 and c2 look swapped" in reason for reason in refused.values())


def in_bgr_order(capture: Path) -> None:
    """Every image written from an RGB array by ``cv2.imwrite`` (which expects BGR): red and blue swapped."""
    for path in (capture / "images").rglob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path))[..., ::-1])


def test_images_in_bgr_order_refuse_the_subject_with_the_fix(capture, tmp_path):
    in_bgr_order(capture)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 1, result.output  # no row was written
    refused = quarantine(tmp_path / "out")
    assert len(refused) == 15
    for entry in refused:
        assert entry["reason"].startswith("check colour-order: subject s1: on the head, blue is above red in")
        assert "write them in RGB order" in entry["reason"]
    doctor = run("doctor", "custom", capture)
    assert doctor.exit_code == 1 and "[override: --accept-check colour-order]" in doctor.output


def test_colour_order_can_be_accepted_for_a_capture_under_blue_light(capture, tmp_path):
    in_bgr_order(capture)
    result = ingest_custom(capture, tmp_path / "out", "--accept-check", "colour-order")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15


def test_upside_down_image_is_quarantined_with_its_orientation(capture, tmp_path):
    path = capture / "images" / "s1" / "000000" / "c3.png"
    cv2.imwrite(str(path), cv2.imread(str(path))[::-1, ::-1])
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    [entry] = quarantine(tmp_path / "out")
    assert entry["item"] == "s1/000000/c3/full" and entry["stage"] == "check"
    assert "upside down relative to its mask" in entry["reason"]


def other_pose_mesh(capture: Path) -> None:
    """Frame 1 gets the mesh of a head pose 8 degrees and 13 mm away from what its images show."""
    template = make_template(12)
    angle = np.radians(8.0)
    tilt = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    wrong = head_pose(1) @ similarity(1.0, tilt, [0.013, 0.0, 0.0])
    write_obj(
        capture / "meshes" / "s1" / "000001.obj", transform_points(wrong, template.vertices), template.faces
    )


def test_mesh_of_another_pose_quarantines_the_frame(capture, tmp_path):
    other_pose_mesh(capture)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = quarantine(tmp_path / "out")
    assert {e["item"] for e in refused} == {f"s1/000001/c{k}/full" for k in range(5)}
    assert all("mesh of another frame or head pose" in e["reason"] for e in refused)


def swap_frame_images(capture: Path, first: str, second: str, cameras=("c0", "c1", "c2", "c3", "c4")) -> None:
    """The images of two frames exchanged for ``cameras``, as when image folders are numbered wrongly."""
    for camera in cameras:
        a, b = (capture / "images" / "s1" / frame / f"{camera}.png" for frame in (first, second))
        a_bytes, b_bytes = a.read_bytes(), b.read_bytes()
        a.write_bytes(b_bytes)
        b.write_bytes(a_bytes)


def test_images_of_two_frames_exchanged_refuse_both_frames_as_mispaired(capture, tmp_path):
    """Frames 0 and 2 (6 degrees, 8 mm apart) exchange their images. Most views still agree with the wrong
    mesh within the held-back margin, and the frame comparison sees two of three frames disagree without
    telling which; a view of each frame showing the other's head names the exchange, and every view of
    both frames is refused, rows already written included."""
    swap_frame_images(capture, "000000", "000002")
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = {e["item"]: e["reason"] for e in quarantine(tmp_path / "out")}
    assert set(refused) == {f"s1/00000{f}/c{k}/full" for f in (0, 2) for k in range(5)}
    for item, reason in refused.items():
        other = "2" if item.split("/")[1] == "000000" else "0"
        assert f"judged images show the head of frame {other}, and frame {other}'s images that of" in reason
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 5  # frame 1's images are its own


def test_one_image_of_another_frame_is_named_with_that_frame(capture, tmp_path):
    folder = capture / "images" / "s1"
    (folder / "000000" / "c3.png").write_bytes((folder / "000002" / "c3.png").read_bytes())
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    [entry] = quarantine(tmp_path / "out")
    assert entry["item"] == "s1/000000/c3/full"
    assert "the image of camera c3 shows the head of frame 2" in entry["reason"]


def test_view_partly_off_its_foreground_in_a_good_frame_is_written_after_all(capture, tmp_path, monkeypatch):
    """A view held back as doubtful (part of the head dark, as under black hair) is released when its
    frame agrees with the subject's other frames."""
    path = capture / "images" / "s1" / "000001" / "c2.png"
    image = cv2.imread(str(path))
    rows = np.flatnonzero(image.max(axis=(1, 2)) > 0)
    image[rows[0] : rows[0] + (rows[-1] - rows[0]) // 8] = 0
    cv2.imwrite(str(path), image)
    decoded: list[str] = []
    decode = TaskDecoder.decode
    monkeypatch.setattr(
        TaskDecoder, "decode", lambda self, ref: decoded.append(ref.label) or decode(self, ref)
    )
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    dataset = NormalizedDataset(tmp_path / "out" / "custom")
    assert len(dataset) == 15
    # The held view's row was kept, not decoded again, and is the row an ingest that holds nothing writes.
    assert len(decoded) == len(set(decoded)) == 15, decoded
    unheld = ingest_custom(capture, tmp_path / "unheld", "--accept-check", "silhouette")
    assert unheld.exit_code == 0, unheld.output
    key = next(k for k in dataset.keys if "/c2/" in k and "/000001/" in k)
    unheld_row = NormalizedDataset(tmp_path / "unheld" / "custom").row(key)
    assert dataset.row(key).to_arrow_dict() == unheld_row.to_arrow_dict()


def test_head_half_in_black_shadow_passes_with_no_finding(capture, tmp_path):
    """Skin in deep shadow is as black as the backdrop: with one side of the head pure black in every view
    of a frame, the head is half off the foreground, yet the foreground lies on the head."""
    for path in sorted((capture / "images" / "s1" / "000001").glob("*.png")):
        image = cv2.imread(str(path))
        columns = np.flatnonzero(image.max(axis=(0, 2)) > 0)
        image[:, (columns[0] + columns[-1]) // 2 :] = 0
        cv2.imwrite(str(path), image)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15


def test_mismatched_frames_need_other_frames_to_compare_with():
    shares = {0: [1.0, 0.99, 1.0], 1: [0.9, 0.93, 0.91], 2: [1.0, 0.98]}
    bad, baseline = mismatched_frames(shares)
    assert set(bad) == {1} and baseline == pytest.approx(0.99)
    assert mismatched_frames({1: [0.9, 0.93, 0.91]})[0] == {}
    assert mismatched_frames({0: [0.95, 0.96], 1: [0.95, 0.94]})[0] == {}


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


# ------------------------------------------------------------------------ failures of more than a view
def move_meshes(capture: Path, offset: tuple[float, float, float]) -> None:
    """Every frame's mesh moved by ``offset`` (m) in the capture's world: the tracking of other images
    (another sequence of the subject, the head a few centimetres elsewhere)."""
    for path in sorted((capture / "meshes").rglob("*.obj")):
        vertices, faces = read_obj(path)
        write_obj(path, vertices + np.asarray(offset), faces)


def test_tracking_of_other_images_refuses_the_whole_subject(capture, tmp_path):
    move_meshes(capture, (0.06, 0.0, 0.04))
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 1 and "no row was written" in result.output, result.output
    assert "most frequent: check silhouette: subject s1: " in result.output
    refused = quarantine(tmp_path / "out")
    assert len(refused) == 15
    assert all("the tracking is not of these images" in e["reason"] for e in refused)
    assert all("--sequence" in e["reason"] and e["stage"] == "check" for e in refused)
    # A dataset without rows has nothing to overlay: said in one line, no traceback.
    overlay = run("inspect", tmp_path / "out" / "custom", "--overlay", tmp_path / "overlay.png")
    assert overlay.exit_code == 1 and "has no image rows to draw" in overlay.output
    assert "Traceback" not in overlay.output


def test_a_camera_wrong_in_every_frame_is_refused_as_a_whole(capture, tmp_path):
    """c3's rotation is 6 degrees off: it still faces the head, so only its images show the fault, in
    every frame, whatever each view's own verdict guesses."""
    path = capture / "cameras.json"
    document = json.loads(path.read_text())
    angle = np.radians(6.0)
    turn = np.eye(4)
    turn[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    document["cameras"]["c3"]["w2c"] = (turn @ np.array(document["cameras"]["c3"]["w2c"])).tolist()
    path.write_text(json.dumps(document))
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = {e["item"]: e["reason"] for e in quarantine(tmp_path / "out")}
    assert set(refused) == {f"s1/00000{f}/c3/full" for f in range(3)}
    assert all("camera c3" in r and "a fault of the camera itself" in r for r in refused.values())
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 12
    # The image check runs while writing; the summary names what it quarantined.
    assert "each image is checked as it is written" in result.output
    assert "a fault of the camera itself" in result.output and "(3 views)" in result.output


def test_an_image_of_another_camera_in_a_second_file_is_not_written_for_the_first(capture, tmp_path):
    """Two files for one view (``c0.png`` and ``c0.jpg``, the second showing c2's view): the first in
    order is kept, and its own row is the one written."""
    folder = capture / "images" / "s1" / "000000"
    cv2.imwrite(str(folder / "c0.jpg"), cv2.imread(str(folder / "c2.png")), [cv2.IMWRITE_JPEG_QUALITY, 100])
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    dataset = NormalizedDataset(tmp_path / "out" / "custom")
    row = dataset.row(next(k for k in dataset.keys if "/000000/c0/" in k))
    [entry] = [e for e in quarantine(tmp_path / "out") if e["item"] == "s1/000000/c0/full"]
    assert row.source != entry["source"]
    assert row.source.endswith(("c0.png", "c0.jpg")) and entry["source"].endswith(("c0.png", "c0.jpg"))


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


def test_background_is_found_when_the_head_reaches_the_border_away_from_its_mask():
    image = np.zeros((40, 30, 3), np.float32)
    image[10:30, 0:12] = 0.6  # the head, touching the left border
    expected = np.zeros((40, 30), bool)
    expected[10:30, 18:30] = True  # where the mesh says it is: the image is mirrored
    foreground = image_foreground(image, expected)
    assert foreground is not None and foreground.sum() == 20 * 12 and foreground[10:30, 0:12].all()
    image[:, :, 1] = np.linspace(0, 0.5, 30)[None]  # a border with no dominant colour: cannot tell
    assert image_foreground(image, expected) is None


def test_outline_is_the_hull_of_every_vertex():
    """The 3D hull's vertices outline a head exactly as all of its vertices do; an evenly spaced subsample
    misses the extreme ones (here the outline of 150 of them covers clearly less)."""
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(6000, 3))
    radii = np.where(rng.random(6000) < 0.5, 1.0, rng.uniform(0.5, 0.95, 6000))[
        :, None
    ]  # a surface and inside
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * radii * [0.08, 0.11, 0.09]
    K = np.array([[300.0, 0, 47.5], [0, 300.0, 63.5], [0, 0, 1]])
    w2c = look_at_w2c(np.array([0.3, 0.1, 0.8]), np.zeros(3))
    everything = hull_mask(points, K, w2c, (96, 128))
    hull = points[hull_indices(points)]
    assert np.array_equal(hull_mask(hull, K, w2c, (96, 128)), everything)
    assert len(hull) < len(points) / 2
    assert hull_mask(subsample(points, 150), K, w2c, (96, 128)).sum() < 0.95 * everything.sum()


def test_head_mostly_black_like_dark_hair_passes_with_no_finding(capture, tmp_path):
    """The upper 60 % of the head as black as the backdrop in every view: the foreground still lies on
    the head's outline, so nothing is refused (no view, camera or subject)."""
    for path in sorted((capture / "images" / "s1").rglob("*.png")):
        image = cv2.imread(str(path))
        rows = np.flatnonzero(image.max(axis=(1, 2)) > 0)
        image[: rows[0] + int(0.6 * (rows[-1] - rows[0]))] = 0
        cv2.imwrite(str(path), image)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15


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
