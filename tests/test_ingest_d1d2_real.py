"""Real FaceOLAT and Ava-256 calibration, light and colour files, in minimal folders around them with
tiny stand-in images, plan into sane rigs."""

from __future__ import annotations

import io
import json
import shutil
import zipfile

import numpy as np
import pytest
from PIL import Image
from scipy.optimize import least_squares

from relightanyone.ingest import ava256, faceolat
from relightanyone.ingest.records import AdapterOptions
from relightanyone.synth.envmap import write_exr

FACEOLAT_SIZE = (135, 256)  # 2160x4096 / 16: the same aspect ratio as the calibration
AVA_SIZE = (667, 1024)  # the 4TB release: 2668x4096 / 4


def convergence_point(centres: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(3,) least-squares point closest to every optical axis."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c, d in zip(centres, directions, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    return np.linalg.solve(A, b)


def camera_axes(views) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) and viewing directions (N, 3) of distinct cameras of a list of views."""
    cams = {v.camera.name: v.camera for v in views}
    centres = np.array([-c.w2c[:3, :3].T @ c.w2c[:3, 3] for c in cams.values()])
    directions = np.array([c.w2c[2, :3] for c in cams.values()])
    return centres, directions


@pytest.fixture(scope="module")
def faceolat_folder(real_fixtures, tmp_path_factory):
    """Subjects 001 (complete calibration) and 012 (incomplete), 40 cameras, frames 0 and 1 each."""
    real = real_fixtures / "faceolat"
    root = tmp_path_factory.mktemp("faceolat_real") / "faceolat"
    (root / "calibration/cameras").mkdir(parents=True)
    (root / "color-calibration").mkdir()
    (root / "relighting/lights").mkdir(parents=True)
    for subject in ("001", "012"):
        shutil.copy(real / f"{subject}.xml", root / f"calibration/cameras/{subject}.xml")
    shutil.copy(real / "colorcalib_exr.mat", root / "color-calibration/colorcalib_exr.mat")
    for name in ("light_pattern_metadata.json", "light_pattern_per_frame.json"):
        shutil.copy(real / name, root / "relighting/lights" / name)
    image = np.full((FACEOLAT_SIZE[1], FACEOLAT_SIZE[0], 3), 0.25, dtype=np.float32)
    for subject in ("001", "012"):
        capture = f"ID20{subject}"
        for camera in range(1, 41):
            for frame in (0, 1):
                write_exr(
                    root / f"{subject}/OutputEXR/Cam{camera:02d}/{capture}/{capture}.{frame:06d}.exr",
                    image,
                    half=True,
                )
    return root


def test_faceolat_real_rig_is_sane(faceolat_folder, real_fixtures):
    plan = faceolat.plan(faceolat_folder, AdapterOptions(subjects=("001",)))
    (subject,) = plan.subjects
    assert len({v.camera.name for v in subject.views}) == 40
    schedule = json.loads((real_fixtures / "faceolat/light_pattern_per_frame.json").read_text())
    expected_full = sorted(frame for frame, pattern in schedule if pattern == 0)
    found_full = plan.found["schedules"]["001/ID20001"]["full_on_frames"]
    assert found_full == expected_full and len(found_full) == 18
    assert {v.pattern for v in subject.views if v.frame == 0} == {"full"}
    pattern_of_1 = dict(schedule)[1]
    assert {v.pattern for v in subject.views if v.frame == 1} == {f"olat-{pattern_of_1 - 1:03d}"}
    # Every other scheduled frame is missing from this minimal folder and is refused, per camera.
    assert len(subject.refusals) == 40 * (len(schedule) - 2)

    # 331 lights on a dome of r ~ 1.7 m, in the calibration's world, around which the cameras converge.
    assert plan.light_positions.shape == (331, 3) and plan.light_intensities.shape == (331, 3)
    fit = least_squares(
        lambda x: np.linalg.norm(plan.light_positions - x[:3], axis=1) - x[3],
        np.r_[plan.light_positions.mean(0), 1.0],
    )
    centre, radius = fit.x[:3], fit.x[3]
    assert 1.6 < radius < 1.8 and np.abs(fit.fun).max() < 0.01
    centres, directions = camera_axes(subject.views)
    assert np.linalg.norm(convergence_point(centres, directions) - centre) < 0.3
    towards = (centre - centres) / np.linalg.norm(centre - centres, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((towards * directions).sum(1), -1, 1))).max() < 15

    # K rescaled from 2160x4096 to the stored 135x256 with the half-pixel rule.
    view = subject.views[0]
    assert (view.camera.width, view.camera.height) == FACEOLAT_SIZE
    assert 18000 / 16 < view.camera.K[1, 1] < 18500 / 16
    M = np.loadtxt(real_fixtures / "faceolat/colorcalib_exr.mat")
    np.testing.assert_allclose(view.colour.matrix, M[:3, :3])
    np.testing.assert_allclose(view.colour.black, M[:3, 3])


def test_faceolat_incomplete_calibration_refuses_uncalibrated_cameras(faceolat_folder):
    plan = faceolat.plan(faceolat_folder, AdapterOptions(subjects=("012",), frames=(0,)))
    (subject,) = plan.subjects
    cameras = {v.camera.name for v in subject.views}
    camera_refusals = {r.item.split("/")[1]: r.reason for r in subject.refusals if r.item.count("/") == 1}
    assert len(cameras) == 22 and len(camera_refusals) == 18
    assert not cameras & set(camera_refusals)
    assert all("not calibrated" in reason for reason in camera_refusals.values())
    assert "Cam02" in camera_refusals


@pytest.fixture(scope="module")
def ava_folder(real_fixtures, tmp_path_factory):
    """One capture around the real 80-camera calibration: identity head pose, one AVIF per camera."""
    root = tmp_path_factory.mktemp("ava_real") / "ava256"
    decoder = root / "20230405--1635--AAN112" / "decoder"
    (decoder / "image").mkdir(parents=True)
    (decoder / "head_pose").mkdir()
    calibration = real_fixtures / "ava-256/full_rig_6933dab/camera_calibration.json"
    shutil.copy(calibration, decoder / "camera_calibration.json")
    (decoder / "frame_list.csv").write_text("seg_id,frame_id\nEXP_neutral_peak,21924\nEXP_free_face,22000\n")
    pose = "1 0 0 0\n0 1 0 0\n0 0 1 0\n"
    with zipfile.ZipFile(decoder / "head_pose/head_pose.zip", "w") as archive:
        archive.writestr("021924.txt", pose)
        archive.writestr("022000.txt", pose)
    buffer = io.BytesIO()
    Image.new("RGB", AVA_SIZE, (60, 50, 40)).save(buffer, format="AVIF", quality=30, speed=10)
    for entry in json.loads(calibration.read_text())["KRT"]:
        camera = entry["cameraId"]
        with zipfile.ZipFile(
            decoder / f"image/cam{camera}.zip", "w", compression=zipfile.ZIP_STORED
        ) as archive:
            archive.writestr(f"cam{camera}/021924.avif", buffer.getvalue())
    return root


def test_ava_real_rig_is_sane(ava_folder, real_fixtures):
    plan = ava256.plan(ava_folder, AdapterOptions())
    (subject,) = plan.subjects
    assert subject.subject == "AAN112" and not subject.refusals
    assert len(subject.views) == 80 and {v.frame for v in subject.views} == {21924}
    data = json.loads((real_fixtures / "ava-256/full_rig_6933dab/camera_calibration.json").read_text())
    entry = data["KRT"][0]
    K_sensor = np.array(entry["K"]).T
    view = next(v for v in subject.views if v.camera.name == entry["cameraId"])
    assert (view.camera.width, view.camera.height) == AVA_SIZE
    np.testing.assert_allclose(view.camera.K[0, 0], K_sensor[0, 0] / 4)
    np.testing.assert_allclose(view.camera.K[:2, 2], (K_sensor[:2, 2] + 0.5) / 4 - 0.5)
    # Identity head pose: w2c is the file's, transposed, in metres.
    T = np.array(entry["T"]).T
    np.testing.assert_allclose(view.camera.w2c[:3, 3], T[:3, 3] * 1e-3, atol=1e-9)
    # The dome's cameras sit about a metre from the point their optical axes converge on.
    centres, directions = camera_axes(subject.views)
    target = convergence_point(centres, directions)
    distances = np.linalg.norm(centres - target, axis=1)
    assert 0.7 < distances.min() and distances.max() < 1.6
    assert view.image.codec == "avif-linear"


def test_ava_dropped_frame_on_the_real_rig(ava_folder):
    plan = ava256.plan(ava_folder, AdapterOptions(all_frames=True))
    (subject,) = plan.subjects
    dropped = [r for r in subject.refusals if r.item.endswith("/022000")]
    assert len(dropped) == 80 and all("dropped frame" in r.reason for r in dropped)
