"""Real rigs as they are captured: downscales from image size against sensor size, off-centre principal
points, the native->tracker fit on the whole rig whatever ``--cameras`` keeps, dropped frames."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers.ava_capture import REAL_SENSOR, SENSOR, SUBJECT, downscaled, drop_image, write_ava_capture
from PIL import Image

from relightanyone.cli import cli
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest import ava256
from relightanyone.ingest.calibration import downsample_factor, read_krt_json
from relightanyone.ingest.records import AdapterOptions
from relightanyone.ingest.runner import ingest_dataset

RIG_CALIBRATION = "ava-256/full_rig_6933dab/camera_calibration.json"  # under the real fixtures


@pytest.fixture
def real_calibration(real_fixtures) -> Path:
    """The real 80-camera Ava-256 calibration; skips with the reason when it is not present."""
    path = real_fixtures / RIG_CALIBRATION
    if not path.is_file():
        pytest.skip(f"the real Ava-256 rig calibration is not at {path}")
    return path


def ingest(capture, plan, out):
    return ingest_dataset(plan, capture.tracking, out, "tiny", progress=False, template=capture.template)


@pytest.mark.parametrize("factor", [1, 2, 4, 8, 16])
def test_off_centre_rig_ingests_every_view_at_every_downscale(tmp_path, factor):
    capture = write_ava_capture(tmp_path, factor=factor)
    plan = ava256.plan(capture.root, AdapterOptions(sensor_size=SENSOR))
    assert not [r for s in plan.subjects for r in s.refusals]
    views = plan.subjects[0].views
    assert len(views) == len(capture.cameras) * 2
    for view in views:
        assert (view.camera.width, view.camera.height) == capture.image_size
        np.testing.assert_allclose(view.camera.K, capture.K_image(view.camera.name), atol=1e-9)
    summary = ingest(capture, plan, tmp_path / "out")
    assert summary.rows == len(views) and summary.quarantined == 0
    dataset = NormalizedDataset(summary.path)
    for key in dataset.keys:
        row = dataset.row(key)
        expected = capture.w2c_head[(row.frame, row.camera)]
        np.testing.assert_allclose(row.w2c, expected, atol=1e-6)


def test_a_calibration_for_another_sensor_is_refused_with_the_size_to_pass(tmp_path):
    capture = write_ava_capture(tmp_path, factor=2, cameras=4)
    plan = ava256.plan(capture.root, AdapterOptions())  # read as the 2668x4096 sensor
    reasons = {r.reason for s in plan.subjects for r in s.refusals}
    assert not plan.view_count and len(reasons) == 1
    (reason,) = reasons
    assert "principal points" in reason and "--sensor-size" in reason and "2668x4096" in reason


def test_real_rig_factors_come_from_the_image_size(real_calibration):
    rig = read_krt_json(real_calibration)
    K = rig.K.numpy()
    centre = np.median(K[:, :2, 2], axis=0)
    assert abs(centre[0] - 1482) < 20 and abs(centre[1] - 1710) < 20  # off-centre, as the issue describes
    for factor in (1, 2, 4, 8, 16):
        width, height = REAL_SENSOR[0] / factor, REAL_SENSOR[1] / factor
        for size in {(int(np.floor(width)), int(height)), (int(np.ceil(width)), int(height))}:
            downscale = downsample_factor(K, size, REAL_SENSOR)
            assert downscale.factor == factor, (size, downscale)
            stored = downscale.intrinsics(K)
            np.testing.assert_allclose(stored[:, 1, 1], K[:, 1, 1] / factor)
            np.testing.assert_allclose(stored[:, 1, 2], (K[:, 1, 2] + 0.5) / factor - 0.5)
    with pytest.raises(ValueError, match="no downscale"):
        downsample_factor(K, (300, 512), REAL_SENSOR)


@pytest.mark.parametrize("factor", [8, 16])
def test_real_rig_capture_plans_every_view_at_small_downscales(real_calibration, tmp_path, factor):
    """The release layout on the real 80-camera calibration, images for three cameras, ``--cameras``."""
    decoder = tmp_path / f"20230405--1635--{SUBJECT}" / "decoder"
    (decoder / "image").mkdir(parents=True)
    (decoder / "head_pose").mkdir()
    (decoder / "camera_calibration.json").write_bytes(real_calibration.read_bytes())
    (decoder / "frame_list.csv").write_text("seg_id,frame_id\nEXP_neutral_peak,7\n")
    with zipfile.ZipFile(decoder / "head_pose" / "head_pose.zip", "w") as archive:
        archive.writestr("000007.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    rig = read_krt_json(real_calibration)
    kept = tuple(rig.names[:3])
    size = downscaled(REAL_SENSOR, factor)
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((size[1], size[0], 3), np.uint8)).save(buffer, format="AVIF", quality=50)
    for camera in kept:
        with zipfile.ZipFile(decoder / "image" / f"cam{camera}.zip", "w") as archive:
            archive.writestr(f"cam{camera}/000007.avif", buffer.getvalue())
    plan = ava256.plan(tmp_path, AdapterOptions(cameras=kept))
    assert not [r for s in plan.subjects for r in s.refusals]
    assert sorted(v.camera.name for v in plan.subjects[0].views) == sorted(kept)
    assert len(plan.subjects[0].rig_w2c) == len(rig.names) == 80  # the fit sees the whole rig
    for view in plan.subjects[0].views:
        index = rig.names.index(view.camera.name)
        K = rig.K[index].numpy()
        np.testing.assert_allclose(view.camera.K[1, 1], K[1, 1] / factor)
        np.testing.assert_allclose(view.camera.K[0, 2], (K[0, 2] + 0.5) * size[0] / REAL_SENSOR[0] - 0.5)


def test_selected_cameras_are_written_with_the_fit_on_the_whole_rig(tmp_path):
    capture = write_ava_capture(tmp_path, factor=4)
    kept = (capture.cameras[1], capture.cameras[3])
    plan = ava256.plan(capture.root, AdapterOptions(sensor_size=SENSOR, cameras=kept))
    summary = ingest(capture, plan, tmp_path / "out")
    assert summary.rows == 4 and summary.quarantined == 0
    assert {
        NormalizedDataset(summary.path).row(k).camera for k in NormalizedDataset(summary.path).keys
    } == set(kept)


def test_a_dropped_frame_quarantines_only_its_own_view(tmp_path):
    capture = write_ava_capture(tmp_path, factor=4)
    kept = tuple(capture.cameras[:3])
    drop_image(capture, kept[1], 14)
    plan = ava256.plan(capture.root, AdapterOptions(sensor_size=SENSOR, cameras=kept))
    summary = ingest(capture, plan, tmp_path / "out")
    assert summary.rows == 5 and summary.quarantined == 1
    keys = NormalizedDataset(summary.path).keys
    assert not any(k.endswith(f"{SUBJECT}/000014/{kept[1]}/full") for k in keys)
    assert downscaled(SENSOR, 4) == capture.image_size


def test_cli_sensor_size_and_dry_run_report_the_downscale(tmp_path):
    capture = write_ava_capture(tmp_path, factor=8, cameras=4)
    args = ["ingest", "ava256", str(capture.root), "--tracking", str(capture.tracking), "--out",
            str(tmp_path / "out"), "--template", str(capture.template), "--preset", "tiny", "--dry-run"]  # fmt: skip
    result = CliRunner().invoke(cli, [*args, "--sensor-size", "167x256"])
    assert result.exit_code == 0, result.output
    assert "21x32 = 167x256 sensor / 8" in result.output and "8 views, 0 refused" in result.output
    refused = CliRunner().invoke(cli, args)  # read as the 2668x4096 sensor: every camera refused, exit 1
    assert refused.exit_code == 1 and "--sensor-size" in refused.output
    bad = CliRunner().invoke(cli, [*args, "--sensor-size", "big"])
    assert bad.exit_code == 2 and "WIDTHxHEIGHT" in bad.output
