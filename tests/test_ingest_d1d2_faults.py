"""Malformed FaceOLAT (D1) and Ava-256 (D2) inputs: a clear error naming the file, or a Refusal when the
rest of the dataset can still be ingested correctly."""

from __future__ import annotations

import json
import re
import shutil
import zipfile

import numpy as np
import pytest
from helpers.small_worlds import make_world, reduced_preset
from PIL import Image

from relightanyone.ingest import ava256, faceolat
from relightanyone.ingest.records import AdapterOptions, LayoutError
from relightanyone.synth.envmap import write_exr
from relightanyone.synth.presets import DatasetSize

MICRO = reduced_preset(
    template_segments=12,
    texture_size=8,
    answer_lights=2,
    d1=DatasetSize(train_subjects=2, test_subjects=0, cameras=2, image_size=(16, 24), lights=4),
    d2=DatasetSize(train_subjects=2, test_subjects=0, cameras=2, image_size=(63, 96), frames=2, lights=4),
)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("world_faults"), MICRO, seed=5, datasets=("d1", "d2"))


@pytest.fixture
def d1(pristine, tmp_path):
    """A private copy of the D1 folder to break."""
    return shutil.copytree(pristine / "faceolat", tmp_path / "faceolat")


@pytest.fixture
def d2(pristine, tmp_path):
    """A private copy of the D2 folder to break."""
    return shutil.copytree(pristine / "ava256", tmp_path / "ava256")


def view_keys(plan) -> list[tuple]:
    return [(v.subject, v.frame, v.camera.name, v.pattern) for s in plan.subjects for v in s.views]


# ------------------------------------------------------------------------------------------------ D1
def test_d1_missing_subject_calibration_is_refused_and_others_kept(d1):
    (d1 / "calibration/cameras/001.xml").unlink()
    plan = faceolat.plan(d1, AdapterOptions())
    by_subject = {s.subject: s for s in plan.subjects}
    assert not by_subject["001"].views
    assert by_subject["001"].refusals[0].source == "calibration/cameras/001.xml"
    assert "no calibration file" in by_subject["001"].refusals[0].reason
    assert by_subject["002"].views and not by_subject["002"].refusals


def test_d1_no_calibration_at_all_names_the_folder(d1):
    shutil.rmtree(d1 / "calibration/cameras")
    with pytest.raises(LayoutError, match="calibration/cameras"):
        faceolat.detect(d1)


def test_d1_missing_colour_matrix_stops_with_the_file(d1):
    (d1 / faceolat.COLOUR_FILE).unlink()
    with pytest.raises(LayoutError, match="colorcalib_exr.mat"):
        faceolat.plan(d1, AdapterOptions())


def test_d1_camera_without_calibration_is_refused_with_metashape_reason(d1):
    xml = d1 / "calibration/cameras/001.xml"
    text = xml.read_text()
    # Drop Cam02's <camera> element and its sensor's calibration, as in FaceOLAT's incomplete takes.
    text = re.sub(r'\s*<camera id="1" [^>]*>.*?</camera>', "", text, flags=re.S)
    text = re.sub(r'(<sensor id="1" .*?)<calibration .*?</calibration>', r"\1", text, flags=re.S)
    xml.write_text(text)
    plan = faceolat.plan(d1, AdapterOptions())
    subject = next(s for s in plan.subjects if s.subject == "001")
    assert {v.camera.name for v in subject.views} == {"Cam01"}
    (refusal,) = [r for r in subject.refusals if r.item == "001/Cam02"]
    assert refusal.source == "calibration/cameras/001.xml" and "not calibrated" in refusal.reason


def test_d1_frames_of_an_unknown_camera_are_refused(d1):
    folder = d1 / "001/OutputEXR"
    shutil.copytree(folder / "Cam01", folder / "Cam77")
    plan = faceolat.plan(d1, AdapterOptions())
    subject = next(s for s in plan.subjects if s.subject == "001")
    assert "Cam77" not in {v.camera.name for v in subject.views}
    assert any(r.item.endswith("/Cam77") and "absent from" in r.reason for r in subject.refusals)


@pytest.mark.parametrize("damage", ["not json", "wrong olat"])
def test_d1_corrupt_light_metadata_stops_with_the_file(d1, damage):
    path = d1 / faceolat.LIGHT_METADATA
    if damage == "not json":
        path.write_text(path.read_text()[:50])
        expected = "not valid JSON"
    else:
        data = json.loads(path.read_text())
        data["light_patterns"][2]["light_index_durations"] = [[3, 4.0]]
        path.write_text(json.dumps(data))
        expected = "pattern 2 must light light 1 alone"
    with pytest.raises(ValueError, match="light_pattern_metadata.json") as error:
        faceolat.plan(d1, AdapterOptions())
    assert expected in str(error.value)


def test_d1_missing_frame_and_corrupt_take_schedule_are_refused(d1):
    (d1 / "001/OutputEXR/Cam01/ID20001/ID20001.000003.exr").unlink()
    (d1 / "002/lights/ID20002/light_pattern_per_frame.json").write_text("[[0, 0], [1")
    plan = faceolat.plan(d1, AdapterOptions())
    by_subject = {s.subject: s for s in plan.subjects}
    missing = [r for r in by_subject["001"].refusals if r.item == "001/ID20001/Cam01/000003"]
    assert missing and "missing" in missing[0].reason
    assert not by_subject["002"].views
    assert "light_pattern_per_frame.json" in by_subject["002"].refusals[0].reason


# ------------------------------------------------------------------------------------------------ D2
def capture(root, index=0):
    return sorted(p for p in root.iterdir() if p.is_dir())[index]


def test_d2_truncated_zip_and_unsafe_member_are_refused(d2):
    folder = capture(d2) / "decoder/image"
    zips = sorted(folder.glob("cam*.zip"))
    data = zips[0].read_bytes()
    zips[0].write_bytes(data[: len(data) // 2])
    with zipfile.ZipFile(zips[1], "a") as archive:
        archive.writestr("../x", b"escape")
    plan = ava256.plan(d2, AdapterOptions())
    subject = plan.subjects[0]
    reasons = {r.item: r.reason for r in subject.refusals}
    broken = zips[0].stem[3:]
    assert "unreadable zip" in reasons[f"{subject.subject}/{broken}"]
    assert "unsafe" in reasons[f"{subject.subject}/{zips[1].stem[3:]}/../x"]
    assert broken not in {v.camera.name for v in subject.views}
    assert zips[1].stem[3:] in {v.camera.name for v in subject.views}


def test_d2_camera_absent_from_calibration_is_refused(d2):
    path = capture(d2) / "decoder/camera_calibration.json"
    data = json.loads(path.read_text())
    removed = data["KRT"].pop(0)["cameraId"]
    path.write_text(json.dumps(data))
    plan = ava256.plan(d2, AdapterOptions())
    subject = plan.subjects[0]
    assert removed not in {v.camera.name for v in subject.views}
    assert any(
        r.item == f"{subject.subject}/{removed}" and "absent from" in r.reason for r in subject.refusals
    )


def test_d2_nan_calibration_refuses_that_capture_naming_file_and_field(d2):
    path = capture(d2) / "decoder/camera_calibration.json"
    data = json.loads(path.read_text())
    data["KRT"][1]["T"][3][0] = float("nan")
    path.write_text(json.dumps(data))
    plan = ava256.plan(d2, AdapterOptions())
    first, second = plan.subjects
    assert not first.views and second.views
    reason = first.refusals[0].reason
    assert "camera_calibration.json" in reason and "KRT[1]" in reason and "NaN" in reason


def test_d2_missing_head_pose_refuses_that_frame(d2):
    path = capture(d2) / "decoder/head_pose/head_pose.zip"
    with zipfile.ZipFile(path) as archive:
        members = {n: archive.read(n) for n in archive.namelist()}
    neutral = sorted(members)[0]
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            if name != neutral:
                archive.writestr(name, data)
    plan = ava256.plan(d2, AdapterOptions())
    subject = plan.subjects[0]
    assert not subject.views
    assert any("no head pose" in r.reason for r in subject.refusals)


def test_d2_missing_calibration_file_names_it(d2):
    for folder in sorted(p for p in d2.iterdir() if p.is_dir()):
        (folder / "decoder/camera_calibration.json").unlink()
    with pytest.raises(LayoutError, match="camera_calibration.json"):
        ava256.plan(d2, AdapterOptions())


def test_d2_not_an_ava_folder(tmp_path):
    with pytest.raises(LayoutError, match="no capture found"):
        ava256.detect(tmp_path)


# ------------------------------------------------------------------------------------------------ D1 layouts
def test_d1_avif_export_is_detected_with_gamma_and_colour_already_applied(d1):
    for exr in sorted(d1.glob("*/OutputEXR/*/*/*.exr")):
        relative = exr.relative_to(d1).as_posix().replace("OutputEXR", "OutputAVIF")
        target = (d1 / relative).with_suffix(".avif")
        target.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", MICRO.d1.image_size, (90, 80, 70)).save(target, format="AVIF", quality=50, speed=10)
    reference = faceolat.plan(d1, AdapterOptions())
    for folder in sorted(d1.glob("*/OutputEXR")):
        shutil.rmtree(folder)
    assert faceolat.detect(d1) == "processed-avif"
    plan = faceolat.plan(d1, AdapterOptions())
    assert reference.layout_version == "processed-exr"
    views = [(v.subject, v.frame, v.camera.name, v.pattern) for s in plan.subjects for v in s.views]
    assert views == [
        (v.subject, v.frame, v.camera.name, v.pattern) for s in reference.subjects for v in s.views
    ]
    view = plan.subjects[0].views[0]
    assert view.image.codec == "avif-gamma22" and view.image.path.endswith(".avif")
    assert (view.camera.width, view.camera.height) == MICRO.d1.image_size
    assert abs(view.colour.matrix - [[1, 0, 0], [0, 1, 0], [0, 0, 1]]).max() == 0


def test_d1_frames_in_a_shared_output_folder_belong_to_their_capture_subject(d1):
    reference = faceolat.plan(d1, AdapterOptions())
    for camera_dir in sorted(d1.glob("*/OutputEXR/*")):
        for capture_dir in sorted(camera_dir.iterdir()):
            shutil.copytree(capture_dir, d1 / "OutputEXR" / camera_dir.name / capture_dir.name)
        shutil.rmtree(camera_dir)
    plan = faceolat.plan(d1, AdapterOptions())
    assert [s.subject for s in plan.subjects] == ["001", "002"]
    assert view_keys(plan) == view_keys(reference) and plan.view_count > 0
    assert plan.subjects[0].views[0].source.startswith("OutputEXR/")


def test_d1_corrupt_first_frame_does_not_stop_planning(d1):
    first = d1 / "001/OutputEXR/Cam01/ID20001/ID20001.000000.exr"
    first.write_bytes(first.read_bytes()[:40])
    plan = faceolat.plan(d1, AdapterOptions())
    subject = next(s for s in plan.subjects if s.subject == "001")
    cam01 = [v for v in subject.views if v.camera.name == "Cam01"]
    assert cam01 and (cam01[0].camera.width, cam01[0].camera.height) == MICRO.d1.image_size
    assert any(v.frame == 0 for v in cam01)  # the runner quarantines it when decoding fails


def test_d1_frames_of_another_aspect_ratio_refuse_the_camera(d1):
    square = np.full((16, 16, 3), 0.5, dtype=np.float32)
    for path in sorted((d1 / "001/OutputEXR/Cam02/ID20001").glob("*.exr")):
        write_exr(path, square, half=True)
    plan = faceolat.plan(d1, AdapterOptions())
    subject = next(s for s in plan.subjects if s.subject == "001")
    assert "Cam02" not in {v.camera.name for v in subject.views}
    (refusal,) = [r for r in subject.refusals if r.item == "001/Cam02"]
    assert "no downscale" in refusal.reason and "16x16" in refusal.reason


def test_d2_missing_frame_list_refuses_that_capture(d2):
    (capture(d2, 1) / "decoder/frame_list.csv").unlink()
    plan = ava256.plan(d2, AdapterOptions())
    first, second = plan.subjects
    assert first.views and not second.views
    assert second.refusals[0].source.endswith("decoder/frame_list.csv")
    assert "frame list not found" in second.refusals[0].reason
