"""Real calibration files: the rigs must look at one subject from plausible distances."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from relightanyone.ingest.calibration import read_krt_json, read_krt_text
from relightanyone.ingest.metashape import read_metashape_xml
from relightanyone.render.camera import Cameras


def convergence(cams: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares point nearest to every camera's image-centre ray, and each ray's distance to it.

    The image-centre ray (not the optical axis) is used because some light-stage calibrations put the principal
    point far outside the image.
    """
    centre = torch.stack([(cams.width - 1) / 2.0, (cams.height - 1) / 2.0], dim=-1).double()[:, None]
    origins, directions = cams.rays(centre)
    origins, directions = origins[:, 0].numpy(), directions[:, 0].numpy()
    projectors = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]
    point = np.linalg.solve(projectors.sum(0), np.einsum("bij,bj->i", projectors, origins))
    miss = np.linalg.norm(np.einsum("bij,bj->bi", projectors, point - origins), axis=1)
    return point, miss


def assert_rig_sees_point(cams: Cameras, point: np.ndarray) -> np.ndarray:
    uv, depth = cams.project(torch.tensor(point)[None])
    u, v = uv[:, 0, 0].numpy(), uv[:, 0, 1].numpy()
    assert (depth[:, 0] > 0).all()
    assert ((u >= 0) & (u < cams.width.numpy()) & (v >= 0) & (v < cams.height.numpy())).all()
    return np.linalg.norm(cams.centers.numpy() - point, axis=1)


def test_ava_full_rig_converges_at_one_metre(real_fixtures: Path) -> None:
    cams = read_krt_json(real_fixtures / "ava-256" / "full_rig_6933dab" / "camera_calibration.json")
    assert len(cams) == 80 and len(set(cams.names)) == 80
    point, miss = convergence(cams)
    assert miss.max() < 0.1  # every view centres within 10 cm of one point: the head
    distances = assert_rig_sees_point(cams, point)
    assert 0.8 < distances.min() and distances.max() < 1.4


def test_ava_legacy_krt_has_38_cameras_looking_at_one_point(real_fixtures: Path) -> None:
    cams = read_krt_text(real_fixtures / "ava-256" / "KRT", image_size=(1334, 2048))
    assert len(cams) == 38
    point, miss = convergence(cams)
    assert np.median(miss) < 0.05
    assert_rig_sees_point(cams, point)


def test_faceolat_001_complete_rig(real_fixtures: Path) -> None:
    rig = read_metashape_xml(real_fixtures / "faceolat" / "001.xml")
    assert rig.missing == {} and len(rig.cameras) == 40
    assert rig.cameras.names == tuple(f"Cam{i:02d}" for i in range(1, 41))
    assert abs(rig.chunk_scale - 1.3568618697765547) < 1e-12 and rig.metres_per_unit == 1.0
    assert rig.cameras.width.tolist() == [2160] * 40 and rig.cameras.height.tolist() == [4096] * 40
    point, miss = convergence(rig.cameras)
    assert miss.max() < 0.2 and np.median(miss) < 0.05
    distances = assert_rig_sees_point(rig.cameras, point)
    assert 1.2 < distances.min() and distances.max() < 2.5  # inside the 1.7 m light dome
    R = rig.cameras.R
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(40, 3, 3))


def test_faceolat_012_reports_exactly_the_uncalibrated_cameras(real_fixtures: Path) -> None:
    path = real_fixtures / "faceolat" / "012.xml"
    text = path.read_text()
    sensors = re.findall(r'<sensor id="\d+" label="(Cam\d+)" type="frame">(.*?)</sensor>', text, flags=re.S)
    calibrated = {label for label, body in sensors if "<calibration" in body}
    with_camera = set(
        re.findall(r'<camera id="\d+" sensor_id="\d+" component_id="\d+" label="(Cam\d+)"', text)
    )
    assert len(sensors) == 40 and len(calibrated) == 23 and len(with_camera) == 22

    rig = read_metashape_xml(path)
    expected_missing = {label for label, _ in sensors} - (calibrated & with_camera)
    assert set(rig.missing) == expected_missing and len(rig.missing) == 18
    assert rig.missing["Cam13"] == "no <camera> element"  # calibrated, but never aligned
    assert rig.missing["Cam02"] == "no <camera> element and sensor has no <calibration>"
    assert set(rig.cameras.names) == calibrated & with_camera and len(rig.cameras) == 22
    assert abs(rig.chunk_scale - 0.032348129976269541) < 1e-12
    assert torch.isfinite(rig.cameras.K).all() and torch.isfinite(rig.cameras.w2c).all()
    _, miss = convergence(rig.cameras)
    assert np.median(miss) < 0.05
