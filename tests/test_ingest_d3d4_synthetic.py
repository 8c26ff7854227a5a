"""Stereo rig (D3) and NeRSemble v1/v2 (D4) adapters against the synthetic world's ground truth.

The world is a reduced tiny preset (two subjects, five NeRSemble cameras, small images). NeRSemble v1 is
tested on a v1 layout converted from the synthetic v2 release inside the test: video frames become PNGs,
the intrinsics are written for a sensor twice the PNG size (as the real v1 release), and each camera gets
an affine colour correction.
"""

from __future__ import annotations

import json
import shutil

import av
import cv2
import numpy as np
import pycolmap
import pytest
from helpers.small_worlds import make_world, reduced_preset
from helpers.synth_judge import project, subject_vertices, truth_of

from relightanyone.align.colour import linear_to_srgb, srgb_to_linear
from relightanyone.align.geometry import transform_points
from relightanyone.ingest import nersemble, stereo_rig
from relightanyone.ingest.records import AdapterOptions, DatasetPlan, LayoutError
from relightanyone.synth.presets import DatasetSize

SMALL = reduced_preset(
    # The chart must stay detectable by cv2.mcc: D3 keeps the tiny preset's 160x120 frames.
    d3=DatasetSize(train_subjects=2, test_subjects=0, cameras=8, image_size=(160, 120), lights=4),
    d4=DatasetSize(train_subjects=2, test_subjects=0, cameras=5, image_size=(64, 96), frames=2, lights=8),
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("world_d3d4"), SMALL, seed=5, datasets=("d3", "d4"))


def assert_projects_like_truth(world, dataset: str, plan: DatasetPlan) -> int:
    """Every planned view's camera, fed the true posed vertices in the native world, lands where the truth
    camera drew them (< 0.1 px). Returns the number of views checked."""
    truth = truth_of(world, dataset)
    checked = 0
    for subject_plan in plan.subjects:
        vertices = subject_vertices(world, dataset, subject_plan.subject)
        for view in subject_plan.views:
            posed = transform_points(truth.head_poses[(subject_plan.subject, view.frame)], vertices)
            cam = truth.cameras[view.camera.name]
            expected = project(cam.K, cam.w2c, cam.dist, posed)
            native = transform_points(truth.world_from_canonical, posed)
            got = project(view.camera.K, view.camera.w2c, view.camera.dist, native)
            assert (view.camera.width, view.camera.height) == (cam.width, cam.height)
            assert np.abs(got - expected).max() < 0.1, (subject_plan.subject, view.frame, view.camera.name)
            checked += 1
    return checked


def refusals_of(plan: DatasetPlan) -> list:
    return list(plan.refusals) + [r for s in plan.subjects for r in s.refusals]


# ------------------------------------------------------------------------------------------------ D3
@pytest.fixture(scope="module")
def d3_plan(world) -> DatasetPlan:
    return stereo_rig.plan(world / "stereo_rig", AdapterOptions())


def test_d3_detects_binary_colmap_model(world):
    assert stereo_rig.detect(world / "stereo_rig") == "colmap-binary"


def test_d3_cameras_project_like_truth(world, d3_plan):
    truth = truth_of(world, "d3")
    assert not refusals_of(d3_plan)
    assert (
        assert_projects_like_truth(world, "d3", d3_plan) == len(d3_plan.subjects) * len(truth.cameras) == 16
    )
    view = d3_plan.subjects[0].views[0]
    assert view.image.codec == "dng-raw" and view.source == f"captures/{view.subject}/{view.camera.name}.dng"
    assert view.pattern == "full" and view.frame == 0


def test_d3_chart_fit_recovers_the_inverse_response(world, d3_plan):
    """The fitted matrix undoes the camera response up to one scale: the chart's irradiance."""
    truth = truth_of(world, "d3")
    scales = []
    for view in d3_plan.subjects[0].views:
        product = view.colour.matrix @ truth.colour_response[view.camera.name]
        scale = np.trace(product) / 3
        np.testing.assert_allclose(product / scale, np.eye(3), atol=0.04)
        scales.append(scale)
        assert view.colour.space == "linear" and "colorchecker" in view.colour.source
    # One lighting for all charts: every camera lands on the same exposure, near the reflectance scale.
    assert np.ptp(scales) < 0.03 * np.mean(scales)
    assert 0.75 < np.mean(scales) < 1.1


def test_d3_chart_residual_reported_per_camera(world, d3_plan):
    fits = d3_plan.found["chart_fit"]
    assert sorted(fits) == sorted(truth_of(world, "d3").cameras)
    for fit in fits.values():
        assert 0 < fit["delta_e_mean"] < 3 and fit["rmse"] < 0.03


def test_d3_text_model_gives_the_same_cameras(world, d3_plan, tmp_path):
    src = shutil.copytree(world / "stereo_rig", tmp_path / "stereo_rig")
    model = src / "calibration/sparse/0"
    reconstruction = pycolmap.Reconstruction(str(model))
    for path in model.glob("*.bin"):
        path.unlink()
    reconstruction.write_text(str(model))
    assert stereo_rig.detect(src) == "colmap-text"
    text_plan = stereo_rig.plan(src, AdapterOptions(subjects=("P001",), cameras=("cam01", "cam06")))
    assert len(text_plan.subjects[0].views) == 2
    binary = {v.camera.name: v.camera for v in d3_plan.subjects[0].views}
    for view in text_plan.subjects[0].views:
        np.testing.assert_allclose(view.camera.K, binary[view.camera.name].K, atol=1e-9)
        np.testing.assert_allclose(view.camera.w2c, binary[view.camera.name].w2c, atol=1e-9)
        np.testing.assert_allclose(view.camera.dist, binary[view.camera.name].dist, atol=1e-12)


def test_d3_millimetre_model_is_converted_to_metres(world, d3_plan, tmp_path):
    src = shutil.copytree(world / "stereo_rig", tmp_path / "stereo_rig")
    model = src / "calibration/sparse/0"
    reconstruction = pycolmap.Reconstruction(str(model))
    reconstruction.transform(pycolmap.Sim3d(1000.0, pycolmap.Rotation3d(), np.zeros(3)))
    reconstruction.write_binary(str(model))
    rig = json.loads((src / "rig.json").read_text())
    (src / "rig.json").write_text(json.dumps({**rig, "units": "mm"}))
    plan = stereo_rig.plan(src, AdapterOptions(subjects=("P001",), cameras=("cam02",)))
    (view,) = plan.subjects[0].views
    expected = next(v.camera for v in d3_plan.subjects[0].views if v.camera.name == "cam02")
    np.testing.assert_allclose(view.camera.w2c, expected.w2c, atol=1e-9)
    (src / "rig.json").write_text(json.dumps({**rig, "units": "furlong"}))
    with pytest.raises(ValueError, match="rig.json: field .units."):
        stereo_rig.plan(src, AdapterOptions())


def test_d3_selections_and_unknown_camera(world, tmp_path):
    src = shutil.copytree(world / "stereo_rig", tmp_path / "stereo_rig")
    shutil.copy(src / "captures/P001/cam00.dng", src / "captures/P001/cam99.dng")
    (src / "captures/P002/cam03.dng").unlink()
    plan = stereo_rig.plan(src, AdapterOptions(cameras=("cam00", "cam03", "cam99")))
    views = sorted((v.subject, v.camera.name) for s in plan.subjects for v in s.views)
    assert views == [("P001", "cam00"), ("P001", "cam03"), ("P002", "cam00")]
    reasons = {r.item: (r.source, r.reason) for r in refusals_of(plan)}
    assert reasons["P001/cam99"][0] == "captures/P001/cam99.dng"
    assert "absent from the COLMAP model" in reasons["P001/cam99"][1]
    assert reasons["P002/cam03"] == (
        "captures/P002/cam03.dng",
        "missing frame: no RAW file for this calibrated camera",
    )
    assert sorted(plan.found["chart_fit"]) == ["cam00", "cam03"]  # only selected cameras are fitted


def test_d3_camera_without_a_detectable_chart_is_refused(world, tmp_path):
    src = shutil.copytree(world / "stereo_rig", tmp_path / "stereo_rig")
    # A face instead of the chart; a truncated file for another camera.
    shutil.copy(src / "captures/P001/cam02.dng", src / "calibration/colorchecker/cam02.dng")
    data = (src / "calibration/colorchecker/cam05.dng").read_bytes()
    (src / "calibration/colorchecker/cam05.dng").write_bytes(data[:200])
    (src / "calibration/colorchecker/cam06.dng").unlink()
    plan = stereo_rig.plan(src, AdapterOptions())
    refused = {r.item: r for r in plan.refusals}
    assert sorted(refused) == ["cam02", "cam05", "cam06"]
    assert refused["cam02"].source == "calibration/colorchecker/cam02.dng"
    assert "ColorChecker" in refused["cam02"].reason
    assert "cam05.dng" in refused["cam05"].reason and "RAW/DNG" in refused["cam05"].reason
    assert "no colour chart frame" in refused["cam06"].reason
    cameras = {v.camera.name for s in plan.subjects for v in s.views}
    assert cameras == {"cam00", "cam01", "cam03", "cam04", "cam07"}


def test_d3_invalid_model_stops_naming_the_folder(world, tmp_path):
    from relightanyone.ingest.calibration import CalibrationError

    src = shutil.copytree(world / "stereo_rig", tmp_path / "stereo_rig")
    (src / "calibration/sparse/0/cameras.bin").write_bytes(b"\x01\x02")
    with pytest.raises(CalibrationError, match="sparse/0"):
        stereo_rig.plan(src, AdapterOptions())
    shutil.rmtree(src / "calibration")
    with pytest.raises(LayoutError, match="COLMAP model folder not found"):
        stereo_rig.detect(src)


# ------------------------------------------------------------------------------------------------ D4 v2
@pytest.fixture(scope="module")
def d4_plan(world) -> DatasetPlan:
    return nersemble.plan(world / "nersemble", AdapterOptions())


def test_d4_v2_detected_and_cameras_project_like_truth(world, d4_plan):
    truth = truth_of(world, "d4")
    assert nersemble.detect(world / "nersemble") == "v2"
    assert not refusals_of(d4_plan)
    checked = assert_projects_like_truth(world, "d4", d4_plan)
    assert checked == len(d4_plan.subjects) * len(truth.cameras) * 2 == 20
    assert set(d4_plan.found["sequences"].values()) == {
        "EXP-1-head"
    }  # BACKGROUND is not a sequence to ingest
    view = d4_plan.subjects[0].views[0]
    assert view.image.codec == "mp4-frame" and view.image.frame_index == view.frame
    assert view.source.endswith(f"images/cam_{view.camera.name}.mp4#frame={view.frame}")


def test_d4_v2_colour_calibration_inverts_the_response(world, d4_plan):
    truth = truth_of(world, "d4")
    for view in d4_plan.subjects[0].views:
        np.testing.assert_allclose(
            view.colour.matrix @ truth.colour_response[view.camera.name], np.eye(3), atol=1e-9
        )
        assert view.colour.space == "linear" and view.colour.source.endswith(
            "calibration/color_calibration.json"
        )


def test_d4_frame_past_the_end_and_sequence_choice(world):
    plan = nersemble.plan(world / "nersemble", AdapterOptions(frames=(1, 5), cameras=("222200042",)))
    refused = refusals_of(plan)
    assert [v.frame for s in plan.subjects for v in s.views] == [1, 1]
    assert len(refused) == 2 and all("the video has 2 frames" in r.reason for r in refused)
    assert refused[0].source.endswith("sequences/EXP-1-head/images/cam_222200042.mp4#frame=5")
    plan = nersemble.plan(world / "nersemble", AdapterOptions(sequence="EXP-2-eyes"))
    assert plan.view_count == 0
    assert all("no sequence EXP-2-eyes" in r.reason for r in refusals_of(plan))


def test_d4_missing_unknown_and_corrupt_videos_are_refused(world, tmp_path):
    src = shutil.copytree(world / "nersemble", tmp_path / "nersemble")
    first, second = sorted(p.name for p in src.iterdir() if p.is_dir())
    videos = src / first / "sequences/EXP-1-head/images"
    (videos / "cam_222200042.mp4").unlink()
    shutil.copy(videos / "cam_222200044.mp4", videos / "cam_999999999.mp4")
    data = (videos / "cam_222200046.mp4").read_bytes()
    (videos / "cam_222200046.mp4").write_bytes(data[: len(data) // 3])
    plan = nersemble.plan(src, AdapterOptions())
    by_subject = {s.subject: s for s in plan.subjects}
    reasons = {r.item: r for r in by_subject[first].refusals}
    assert reasons[f"{first}/222200042"].source == f"{first}/sequences/EXP-1-head/images/cam_222200042.mp4"
    assert "missing video" in reasons[f"{first}/222200042"].reason
    assert "absent from calibration/camera_params.json" in reasons[f"{first}/999999999"].reason
    assert "cam_222200046.mp4" in reasons[f"{first}/222200046"].reason
    assert {v.camera.name for v in by_subject[first].views} == {"222200036", "222200040", "222200044"}
    assert len(by_subject[second].views) == 10 and not by_subject[second].refusals


def test_d4_bad_calibration_refuses_that_participant(world, tmp_path):
    src = shutil.copytree(world / "nersemble", tmp_path / "nersemble")
    first, second = sorted(p.name for p in src.iterdir() if p.is_dir())
    params_path = src / first / "calibration/camera_params.json"
    params = json.loads(params_path.read_text())
    params["world_2_cam"]["222200042"][0][0] = float("nan")
    params_path.write_text(json.dumps(params))
    (src / second / "calibration/color_calibration.json").unlink()
    plan = nersemble.plan(src, AdapterOptions())
    by_subject = {s.subject: s for s in plan.subjects}
    assert not by_subject[first].views and not by_subject[second].views
    (bad_params,) = by_subject[first].refusals
    assert "camera_params.json" in bad_params.reason and "world_2_cam.222200042" in bad_params.reason
    (no_colour,) = by_subject[second].refusals
    assert "color_calibration.json" in no_colour.reason and "not found" in no_colour.reason


def test_d4_singular_colour_matrix_refuses_that_participant(world, tmp_path):
    src = shutil.copytree(world / "nersemble", tmp_path / "nersemble")
    first, second = sorted(p.name for p in src.iterdir() if p.is_dir())
    colour_path = src / first / "calibration/color_calibration.json"
    ccms = json.loads(colour_path.read_text())
    camera = sorted(ccms)[0]
    ccms[camera] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.0]]  # rank 2: blue is lost
    colour_path.write_text(json.dumps(ccms))
    plan = nersemble.plan(src, AdapterOptions())
    by_subject = {s.subject: s for s in plan.subjects}
    assert not by_subject[first].views and by_subject[second].views
    (refusal,) = by_subject[first].refusals
    assert "color_calibration.json" in refusal.reason and f"camera {camera}" in refusal.reason
    assert "singular" in refusal.reason


def test_d4_not_a_nersemble_folder(tmp_path):
    (tmp_path / "017" / "sequences").mkdir(parents=True)
    with pytest.raises(LayoutError, match="neither v2"):
        nersemble.detect(tmp_path)
    with pytest.raises(LayoutError, match="no participant folder"):
        nersemble.detect(tmp_path / "017" / "sequences")


# ------------------------------------------------------------------------------------------------ D4 v1
V1_AFFINE = np.array([[1.03, 0.01, -0.02, 0.01], [0.0, 0.98, 0.01, -0.005], [0.02, -0.01, 1.01, 0.0]])


def write_v1(v2_root, out):
    """Convert a synthetic v2 release into the v1 layout (PNG frames, full-res intrinsics, affine .npy)."""
    for participant in sorted(p for p in v2_root.iterdir() if p.is_dir()):
        target = out / participant.name
        params = json.loads((participant / "calibration/camera_params.json").read_text())
        K = np.array(params["intrinsics"])
        K[:2, :2] *= 2.0  # the calibration is for frames twice the stored PNGs (images-2x)
        K[:2, 2] = (K[:2, 2] + 0.5) * 2.0 - 0.5
        target.mkdir(parents=True)
        (target / "camera_params.json").write_text(
            json.dumps(
                {
                    **params,
                    "intrinsics": K.tolist(),
                    "width": 2 * params["width"],
                    "height": 2 * params["height"],
                }
            )
        )
        for video in sorted((participant / "sequences/EXP-1-head/images").glob("cam_*.mp4")):
            serial = video.stem[len("cam_") :]
            with av.open(str(video)) as container:
                frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
            for t, rgb in enumerate(frames):
                folder = target / f"sequences/EXP-1-head/frame_{t:05d}"
                (folder / "images-2x-73fps").mkdir(parents=True, exist_ok=True)
                (folder / "alpha_map-73fps").mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(folder / f"images-2x-73fps/cam_{serial}.png"), rgb[:, :, ::-1])
                cv2.imwrite(
                    str(folder / f"alpha_map-73fps/cam_{serial}.png"), np.full(rgb.shape[:2], 255, np.uint8)
                )
            colour = target / f"annotations/EXP-1-head/color_correction/{serial}.npy"
            colour.parent.mkdir(parents=True, exist_ok=True)
            np.save(colour, np.vstack([V1_AFFINE, [0.0, 0.0, 0.0, 1.0]]))
    return out


@pytest.fixture(scope="module")
def v1_root(world, tmp_path_factory):
    return write_v1(world / "nersemble", tmp_path_factory.mktemp("nersemble_v1") / "nersemble")


def test_d4_v1_detected_with_half_pixel_intrinsics(world, v1_root, d4_plan):
    assert nersemble.detect(v1_root) == "v1"
    plan = nersemble.plan(v1_root, AdapterOptions())
    assert plan.layout_version == "v1" and plan.found["downsample_factor"] == [2]
    assert not refusals_of(plan)
    assert assert_projects_like_truth(world, "d4", plan) == 20
    v2_cameras = {(v.subject, v.frame, v.camera.name): v.camera for s in d4_plan.subjects for v in s.views}
    for subject_plan in plan.subjects:
        for view in subject_plan.views:
            np.testing.assert_allclose(
                view.camera.K, v2_cameras[(view.subject, view.frame, view.camera.name)].K, atol=1e-9
            )
            assert view.image.codec == "png-srgb" and view.alpha is not None
            assert (
                view.source
                == f"{view.subject}/sequences/EXP-1-head/frame_{view.frame:05d}/images-2x-73fps/cam_{view.camera.name}.png"
            )


def test_d4_v1_affine_applies_in_display_space(v1_root):
    from relightanyone.ingest.decode import apply_colour_calibration

    plan = nersemble.plan(v1_root, AdapterOptions(cameras=("222200042",), frames=(0,)))
    calibration = plan.subjects[0].views[0].colour
    assert calibration.space == "display" and calibration.source.endswith("color_correction/222200042.npy")
    display = np.random.default_rng(0).uniform(0.05, 0.9, size=(4, 5, 3))
    # The v1 loaders: clip(rgb @ A[:3, :3] + A[:3, 3], 0, 1) on the PNG values, then (ours) decode to linear.
    expected = srgb_to_linear(np.clip(display @ V1_AFFINE[:, :3] + V1_AFFINE[:, 3], 0, 1))
    got = apply_colour_calibration(srgb_to_linear(display).astype(np.float32), calibration)
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert np.allclose(
        linear_to_srgb(got), np.clip(display @ V1_AFFINE[:, :3] + V1_AFFINE[:, 3], 0, 1), atol=1e-4
    )


def test_d4_v1_missing_png_and_colour_file_are_refused(v1_root, tmp_path):
    src = shutil.copytree(v1_root, tmp_path / "v1")
    first = sorted(p.name for p in src.iterdir())[0]
    (src / first / "sequences/EXP-1-head/frame_00001/images-2x-73fps/cam_222200040.png").unlink()
    (src / first / "annotations/EXP-1-head/color_correction/222200044.npy").unlink()
    plan = nersemble.plan(src, AdapterOptions(subjects=(first,)))
    reasons = {r.item: r for r in refusals_of(plan)}
    assert sorted(reasons) == [f"{first}/222200040/00001", f"{first}/222200044"]
    assert "missing frame" in reasons[f"{first}/222200040/00001"].reason
    assert "222200044.npy" in reasons[f"{first}/222200044"].reason
    assert plan.view_count == 5 * 2 - 1 - 2
