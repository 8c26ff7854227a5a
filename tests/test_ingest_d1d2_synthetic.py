"""FaceOLAT (D1) and Ava-256 (D2) adapters against the synthetic world's ground truth.

The world is a reduced tiny preset (few cameras, small images, no held-out subjects) so that it renders
in seconds; the layouts, conventions and faults it writes are the tiny preset's.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from helpers.small_worlds import make_world, reduced_preset
from helpers.synth_judge import project, subject_vertices, truth_of

from relightanyone.align.geometry import transform_points
from relightanyone.cli import cli
from relightanyone.ingest import ava256, faceolat
from relightanyone.ingest.records import AdapterOptions, DatasetPlan
from relightanyone.synth.presets import DatasetSize

SMALL = reduced_preset(
    d1=DatasetSize(train_subjects=3, test_subjects=0, cameras=4, image_size=(48, 72), lights=8),
    d2=DatasetSize(train_subjects=2, test_subjects=0, cameras=4, image_size=(52, 80), frames=2, lights=8),
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("world_d1d2"), SMALL, seed=3, datasets=("d1", "d2"))


@pytest.fixture(scope="module")
def d1_plan(world) -> DatasetPlan:
    return faceolat.plan(world / "faceolat", AdapterOptions())


@pytest.fixture(scope="module")
def d2_plan_all(world) -> DatasetPlan:
    return ava256.plan(world / "ava256", AdapterOptions(all_frames=True))


def test_d1_detects_exr_layout(world):
    assert faceolat.detect(world / "faceolat") == "processed-exr"


def test_d1_cameras_project_like_truth(world, d1_plan):
    truth = truth_of(world, "d1")
    checked = 0
    for subject_plan in d1_plan.subjects:
        vertices = subject_vertices(world, "d1", subject_plan.subject)
        seen = set()
        for view in subject_plan.views:
            if view.camera.name in seen:  # every frame of a still take has the same camera
                continue
            seen.add(view.camera.name)
            pose = truth.head_poses[(subject_plan.subject, view.frame)]
            posed = transform_points(pose, vertices)
            cam = truth.cameras[view.camera.name]
            expected = project(cam.K, cam.w2c, cam.dist, posed)
            native = transform_points(truth.world_from_canonical, posed)
            got = project(view.camera.K, view.camera.w2c, view.camera.dist, native)
            assert (view.camera.width, view.camera.height) == (cam.width, cam.height)
            assert np.abs(got - expected).max() < 0.1, (subject_plan.subject, view.camera.name)
            checked += 1
    assert checked == len(d1_plan.subjects) * len(truth.cameras)


def test_d1_colour_calibration_inverts_the_response(world, d1_plan):
    truth = truth_of(world, "d1")
    for view in d1_plan.subjects[0].views[:8]:
        product = view.colour.matrix @ truth.colour_response[view.camera.name]
        np.testing.assert_allclose(product, np.eye(3), atol=1e-6)
        np.testing.assert_array_equal(view.colour.black, np.zeros(3))
        assert view.colour.space == "linear" and view.image.codec == "exr-linear"


def test_d1_full_on_frames_and_patterns_follow_each_take(world, d1_plan):
    truth = truth_of(world, "d1")
    lights = len(truth.light_positions)
    full_sets = set()
    for subject_plan in d1_plan.subjects:
        assert not subject_plan.refusals
        for camera in truth.cameras:
            views = [v for v in subject_plan.views if v.camera.name == camera]
            full = sorted(v.frame for v in views if v.pattern == "full")
            assert full == truth.extra["full_on_frames"][subject_plan.subject]
            olat = sorted(v.pattern for v in views if v.pattern != "full")
            assert olat == [f"olat-{k:03d}" for k in range(lights)]
        full_sets.add(tuple(truth.extra["full_on_frames"][subject_plan.subject]))
    assert len(full_sets) == 2  # one take starts with an extra full-on frame: nothing is hard-coded


def test_d1_lights_map_to_truth(world, d1_plan):
    truth = truth_of(world, "d1")
    expected = transform_points(truth.world_from_canonical, truth.light_positions)
    np.testing.assert_allclose(d1_plan.light_positions, expected, atol=1e-9)
    olat_duration = truth.extra["olat_duration"]
    np.testing.assert_allclose(d1_plan.light_intensities, olat_duration / 5555.0)
    assert d1_plan.kind == "olat" and d1_plan.light_intensities.shape == (len(expected), 3)


@pytest.mark.parametrize("broken", ["calibration", "tracking"])
def test_d1_every_subject_refused_stops_with_the_reasons_and_writes_nothing(world, tmp_path, broken):
    src = shutil.copytree(world / "faceolat", tmp_path / "faceolat")
    tracking = shutil.copytree(world / "tracking", tmp_path / "tracking") / "d1"  # template/ beside d1/
    if broken == "calibration":  # every subject is refused while planning
        for xml in sorted((src / "calibration" / "cameras").glob("*.xml")):
            xml.write_text("<document>")
        cause = "not valid XML"
    else:  # every frame fails to relate to the tracking
        for transforms in sorted(tracking.glob("*/transforms.json")):
            transforms.write_text(transforms.read_text().replace("transform_matrix", "no_matrix"))
        cause = "transform_matrix"
    out = tmp_path / "out"
    result = CliRunner().invoke(
        cli,
        ["ingest", "faceolat", str(src), "--tracking", str(tracking), "--out", str(out), "--preset", "tiny"],
    )
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    lines = result.output.strip().splitlines()
    assert lines[-1].startswith(f"Error: {src}: no frame could be aligned") and cause in lines[-1], lines[-1]
    # Each subject's reason is listed before the error.
    for subject in ("001", "002"):
        assert any(subject in line and cause in line for line in lines[:-1]), result.output
    assert not out.exists()


def test_d2_cameras_project_like_truth(world, d2_plan_all):
    """Head pose folded: the planned camera sees canonical (head-space, metres) vertices where the truth
    camera saw the posed head."""
    truth = truth_of(world, "d2")
    checked = 0
    for subject_plan in d2_plan_all.subjects:
        vertices = subject_vertices(world, "d2", subject_plan.subject)
        for view in subject_plan.views:
            pose = truth.head_poses[(subject_plan.subject, view.frame)]
            cam = truth.cameras[view.camera.name]
            expected = project(cam.K, cam.w2c, cam.dist, transform_points(pose, vertices))
            got = project(view.camera.K, view.camera.w2c, view.camera.dist, vertices)
            assert (view.camera.width, view.camera.height) == (cam.width, cam.height)
            assert np.abs(got - expected).max() < 0.1, (subject_plan.subject, view.frame, view.camera.name)
            checked += 1
    frames = SMALL.d2.frames * SMALL.d2.cameras * SMALL.d2.train_subjects
    assert checked == frames - 1  # every view but the dropped one


def test_d2_dropped_frame_is_refused(world, d2_plan_all):
    dropped = truth_of(world, "d2").extra["dropped_images"][0]
    item = f"{dropped['subject']}/{dropped['camera']}/{dropped['frame_id']:06d}"
    subject_plan = next(s for s in d2_plan_all.subjects if s.subject == dropped["subject"])
    assert [r.item for r in subject_plan.refusals] == [item]
    assert "dropped" in subject_plan.refusals[0].reason
    assert not any(
        v.camera.name == dropped["camera"] and v.frame == dropped["frame_id"] for v in subject_plan.views
    )


def test_d2_neutral_frame_by_default_and_identity_colour(world):
    truth = truth_of(world, "d2")
    plan = ava256.plan(world / "ava256", AdapterOptions())
    for subject_plan in plan.subjects:
        neutral = truth.extra["captures"][subject_plan.subject]["frame_ids"][0]
        assert {v.frame for v in subject_plan.views} == {neutral}
        assert len(subject_plan.views) == SMALL.d2.cameras
        for view in subject_plan.views:
            np.testing.assert_array_equal(view.colour.matrix, np.eye(3))
            assert view.image.codec == "avif-linear" and view.image.member.endswith(f"{neutral:06d}.avif")
    assert plan.kind == "flat" and plan.light_positions is None


def test_d2_frame_selection_by_id(world):
    truth = truth_of(world, "d2")
    subject = sorted(truth.extra["captures"])[0]
    second = truth.extra["captures"][subject]["frame_ids"][1]
    plan = ava256.plan(world / "ava256", AdapterOptions(subjects=(subject,), frames=(second,)))
    assert [s.subject for s in plan.subjects] == [subject]
    assert {v.frame for v in plan.subjects[0].views} == {second}
