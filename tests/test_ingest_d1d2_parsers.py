"""Small parsers and conventions of the FaceOLAT and Ava-256 adapters, on hand-written inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from relightanyone.ingest import ava256, faceolat
from relightanyone.ingest.calibration import downsample_factor
from relightanyone.ingest.records import AdapterOptions


def write(path: Path, data) -> Path:
    path.write_text(json.dumps(data))
    return path


def light_metadata(count: int) -> dict:
    return {
        "light_positions": [[1000.0 * k, 0.0, 2000.0] for k in range(count)],
        "light_patterns": [{"name": "full", "light_index_durations": [[k, 2.0] for k in range(count)]}]
        + [{"name": f"OLAT_{k:03d}", "light_index_durations": [[k, 5555.0 * (k + 1)]]} for k in range(count)],
    }


def test_light_metadata_intensity_is_olat_duration_over_5555(tmp_path):
    rig = faceolat.read_light_metadata(write(tmp_path / "m.json", light_metadata(3)))
    np.testing.assert_allclose(rig.intensities[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(rig.intensities, np.repeat(rig.intensities[:, :1], 3, axis=1))
    np.testing.assert_allclose(rig.full_durations, 2.0)
    np.testing.assert_allclose(rig.positions_mm[2], [2000.0, 0.0, 2000.0])
    assert rig.pattern_names[0] == "full"


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["light_positions"][1].append(4.0), "light_positions"),
        (lambda d: d["light_positions"][1].__setitem__(0, float("nan")), "NaN"),
        (lambda d: d["light_patterns"].pop(), "must hold 4 patterns"),
        (lambda d: d["light_patterns"][0]["light_index_durations"].pop(), "pattern 0 must be full-on"),
        (lambda d: d["light_patterns"][1].pop("light_index_durations"), "light_patterns[1]"),
        (
            lambda d: d["light_patterns"][3]["light_index_durations"][0].__setitem__(1, 0.0),
            "positive durations",
        ),
    ],
)
def test_light_metadata_errors_name_file_and_field(tmp_path, edit, message):
    data = light_metadata(3)
    edit(data)
    path = write(tmp_path / "broken.json", data)
    with pytest.raises(ValueError, match="broken.json") as error:
        faceolat.read_light_metadata(path)
    assert message in str(error.value)


def test_pattern_schedule_and_names(tmp_path):
    schedule = faceolat.read_pattern_schedule(write(tmp_path / "s.json", [[0, 0], [1, 3], [2, 1], [3, 0]]), 4)
    assert faceolat.full_on_frames(schedule) == [0, 3]
    assert [faceolat.pattern_name(schedule[f]) for f in range(4)] == ["full", "olat-002", "olat-000", "full"]


@pytest.mark.parametrize(
    "data, message",
    [
        ([[0, 0], [0, 1]], "frame 0 is listed twice"),
        ([[0, 4]], "pattern 4 is not in 0..3"),
        ([[0, "1"]], "must be [frame, pattern] integers"),
        ({"0": 0}, "non-empty list"),
    ],
)
def test_pattern_schedule_errors(tmp_path, data, message):
    with pytest.raises(ValueError, match="sched.json") as error:
        faceolat.read_pattern_schedule(write(tmp_path / "sched.json", data), 4)
    assert message in str(error.value)


def test_ava_subject_names_from_both_folder_conventions():
    assert ava256.subject_of(Path("20230405--1635--AAN112")) == "AAN112"
    assert ava256.subject_of(Path("m--20230405--1635--AAN112--GHS")) == "AAN112"


def test_ava_downsample_factor():
    K = np.array([[[10000.0, 0, 1413.0], [0, 10000.0, 1783.0], [0, 0, 1]]])
    assert downsample_factor(K, (667, 1024), (2668, 4096)).factor == 4
    assert downsample_factor(K, (1334, 2048), (2668, 4096)).factor == 2
    assert downsample_factor(K, (167, 256), (2668, 4096)).factor == 16  # 2668 / 16 = 166.75, rounded up
    assert downsample_factor(K, (166, 256), (2668, 4096)).factor == 16  # ... or down
    # A calibration made for a smaller sensor: its principal points say so, and the message names the size.
    K_small = np.array([[[800.0, 0, (104 * 4 - 1) / 2 + 3], [0, 800.0, (160 * 4 - 1) / 2 - 2], [0, 0, 1]]])
    with pytest.raises(ValueError, match="they fit a sensor of 416x640: pass --sensor-size"):
        downsample_factor(K_small, (104, 160), (2668, 4096))
    assert downsample_factor(K_small, (104, 160), (416, 640)).factor == 4
    with pytest.raises(ValueError, match="no downscale"):
        downsample_factor(K_small, (150, 160), (416, 640))


def test_ava_frame_selection():
    listed = [("EXP_neutral_peak", 10), ("EXP_free_face", 14), ("EXP_neutral_peak", 30), ("EXP_smile", 18)]
    assert ava256.select_frames(listed, AdapterOptions()) == [10, 30]
    assert ava256.select_frames(listed, AdapterOptions(all_frames=True)) == [10, 14, 18, 30]
    assert ava256.select_frames(listed, AdapterOptions(frames=(14, 99))) == [14]


def test_ava_frame_list_errors(tmp_path):
    path = tmp_path / "frame_list.csv"
    path.write_text("seg,frame\nEXP_neutral_peak,1\n")
    with pytest.raises(ValueError, match="frame_list.csv.*seg_id,frame_id"):
        ava256.read_frame_list(path)
    path.write_text("seg_id,frame_id\nEXP_neutral_peak,one\n")
    with pytest.raises(ValueError, match="line 2"):
        ava256.read_frame_list(path)


def test_k_already_at_the_image_size_is_named():
    K_images = np.array([[[700.0, 0, 180.0], [0, 700.0, 213.0], [0, 0, 1]]])  # off-centre, 334x512 pixels
    with pytest.raises(ValueError, match=r"a sensor of 334x512 \(the images' own size"):
        downsample_factor(K_images, (334, 512), (2668, 4096))
    assert downsample_factor(K_images, (334, 512), (334, 512)).factor == 1
