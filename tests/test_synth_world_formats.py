"""The synthetic world's native writers (D2 Ava-256, D3 stereo rig, D4 NeRSemble), checked against the real
formats they imitate and against their own ground truth, plus the VHAP export and the answers."""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from relightanyone.synth.presets import DatasetSize, get_preset
from relightanyone.synth.raytrace import Scene, SynthCamera, render
from relightanyone.synth.template import make_template, read_obj
from relightanyone.synth.truth import DatasetTruth
from relightanyone.synth.world import generate_world


def micro_preset():
    """A few cameras, small images: the whole world in seconds (D3 keeps a chart-detectable size)."""
    tiny = get_preset("tiny")
    return replace(
        tiny,
        name="micro",
        template_segments=32,
        texture_size=64,
        answer_lights=4,
        envmap_count=1,
        d1=replace(tiny.d1, train_subjects=1, test_subjects=1, cameras=2, image_size=(48, 64)),
        d2=DatasetSize(
            train_subjects=1, test_subjects=1, cameras=4, image_size=(52, 80), frames=2, lights=12
        ),
        d3=DatasetSize(train_subjects=1, test_subjects=1, cameras=8, image_size=(160, 120), lights=4),
        d4=DatasetSize(
            train_subjects=1, test_subjects=1, cameras=16, image_size=(40, 56), frames=2, lights=8
        ),
    )


FLAT = ("d2", "d3", "d4")


@pytest.fixture(scope="session")
def world(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth_world") / "world"
    generate_world(out, micro_preset(), seed=3, datasets=FLAT, progress=False)
    return out


def load_truth(world: Path, dataset: str) -> DatasetTruth:
    return DatasetTruth.load(world / "answers" / dataset / "truth.json")


def subject_shape(world: Path, dataset: str, subject: str) -> np.ndarray:
    vertices, _, _, _ = read_obj(world / "answers" / dataset / "subjects" / subject / "shape.obj")
    return vertices


def frontal_camera(truth: DatasetTruth):
    """The truth camera looking most directly at the face (optical axis closest to -z)."""
    return max(truth.cameras.values(), key=lambda c: -np.linalg.inv(c.w2c)[2, 2])


def drawn_at(world: Path, truth: DatasetTruth, subject: str, camera, vertex: int, pose=None):
    """Render the subject with the truth camera; return (pixel of the vertex by the renderer's camera,
    the set of triangles drawn in the 3x3 window around it, the triangles incident to the vertex)."""
    template = make_template(micro_preset().template_segments)
    vertices = subject_shape(world, truth.dataset, subject)
    scene = Scene(
        vertices if pose is None else vertices @ pose[:3, :3].T + pose[:3, 3],
        template.faces,
        template.uvs,
        template.face_uvs,
        np.full((2, 2, 3), 0.5, np.float32),
        np.zeros((2, 2), np.float32),
        np.ones((2, 2), np.float32),
    )
    cam = SynthCamera(camera.name, camera.K, camera.w2c, camera.width, camera.height, camera.dist)
    result = render(scene, cam, _one_light())
    point = scene.vertices[vertex]
    u, v = cam.project(point[None])[0]
    r0, c0 = int(round(v)), int(round(u))
    window = result.triangle_id[max(r0 - 1, 0) : r0 + 2, max(c0 - 1, 0) : c0 + 2]
    incident = set(np.nonzero((template.faces == vertex).any(axis=1))[0].tolist())
    return np.array([u, v]), set(window.ravel().tolist()), incident, point


def _one_light():
    from relightanyone.synth.raytrace import PointLights

    return PointLights(np.array([[0.0, 0.0, 2.0]]), np.ones((1, 3)))


def nose_tip() -> int:
    return make_template(micro_preset().template_segments).landmarks["nose_tip"]


# ---------------------------------------------------------------------------------------------- D2


def d2_capture(world: Path, truth: DatasetTruth, subject: str) -> Path:
    return world / "ava256" / truth.extra["captures"][subject]["folder"] / "decoder"


def test_d2_calibration_has_the_real_schema(world, real_fixtures):
    real = json.loads((real_fixtures / "ava-256" / "camera_calibration.json").read_text())
    truth = load_truth(world, "d2")
    subject = sorted(truth.splits)[0]
    synthetic = json.loads((d2_capture(world, truth, subject) / "camera_calibration.json").read_text())
    assert set(synthetic) == set(real) == {"KRT"}
    assert len(synthetic["KRT"]) == micro_preset().d2.cameras
    for entry in synthetic["KRT"]:
        assert set(entry) == set(real["KRT"][0])
        assert entry["projectionModel"] == real["KRT"][0]["projectionModel"]
        assert entry["distortionModel"] == real["KRT"][0]["distortionModel"]
        assert len(entry["distortion"]) == len(real["KRT"][0]["distortion"]) == 4
        K, T = np.array(entry["K"]), np.array(entry["T"])
        # Stored transposed as in the real file: K's last ROW is (cx, cy, 1), T's last row the translation.
        assert K[0, 1] == K[0, 2] == K[1, 2] == 0 and K[2, 2] == 1
        assert np.allclose(T[:3, 3], 0) and T[3, 3] == 1
        # Millimetres, like the real rig: the camera centre -R^T t lies ~1.2 m (1200 units) from the head.
        centre = -T[:3, :3] @ T[3, :3]
        assert 1000 < np.linalg.norm(centre - truth.world_from_canonical[:3, 3]) < 1400
        # K is for the real 2668x4096 sensor, of which the written images are a downscale.
        assert 2668 * 0.4 < 2 * K[2, 0] < 2668 * 1.6 and 4096 * 0.4 < 2 * K[2, 1] < 4096 * 1.6


def test_d2_vertex_projects_where_the_renderer_drew_it(world):
    """Decode like Ava-256's loader (transpose K and T, mm, head_pose head->world) and hit the drawn pixel."""
    truth = load_truth(world, "d2")
    subject = sorted(truth.splits)[0]
    decoder = d2_capture(world, truth, subject)
    frame_ids = truth.extra["captures"][subject]["frame_ids"]
    camera = frontal_camera(truth)
    entry = next(
        e
        for e in json.loads((decoder / "camera_calibration.json").read_text())["KRT"]
        if e["cameraId"] == camera.name
    )
    K_sensor = np.array(entry["K"]).T
    Rt = np.array(entry["T"])[:4, :3].T  # 3x4 world(mm) -> camera
    dist = np.array(entry["distortion"] + [0.0])
    width, height = micro_preset().d2.image_size
    s = np.array([2668 / width, 4096 / height])  # the release resizes the full sensor to the stored size
    K_image = K_sensor.copy()
    K_image[[0, 1], [0, 1]] /= s
    K_image[:2, 2] = (K_image[:2, 2] + 0.5) / s - 0.5
    vertex = nose_tip()
    for frame_index, frame_id in enumerate(frame_ids):
        with zipfile.ZipFile(decoder / "head_pose" / "head_pose.zip") as archive:
            head_pose = np.loadtxt(io.BytesIO(archive.read(f"{frame_id:06d}.txt")))
        assert head_pose.shape == (3, 4)
        canonical = subject_shape(world, "d2", subject)[vertex]
        world_mm = head_pose @ np.append(canonical * 1000.0, 1.0)
        rvec, _ = cv2.Rodrigues(Rt[:, :3])
        uv, _ = cv2.projectPoints(world_mm[None], rvec, Rt[:, 3], K_image, dist)
        pose = truth.head_poses[(subject, frame_id)]
        pixel, drawn, incident, _ = drawn_at(world, truth, subject, camera, vertex, pose)
        assert np.linalg.norm(uv.ravel() - pixel) < 1.0, (frame_index, uv.ravel(), pixel)
        assert drawn & incident, f"frame {frame_id}: the renderer did not draw the nose tip at {pixel}"


def test_d2_archives_frame_list_and_dropped_frame(world):
    truth = load_truth(world, "d2")
    width, height = micro_preset().d2.image_size
    dropped = truth.extra["dropped_images"][0]
    for subject in truth.splits:
        decoder = d2_capture(world, truth, subject)
        rows = (decoder / "frame_list.csv").read_text().splitlines()
        assert rows[0] == "seg_id,frame_id" and rows[1].startswith("EXP_neutral_peak,")
        frame_ids = [int(r.split(",")[1]) for r in rows[1:]]
        assert frame_ids == truth.extra["captures"][subject]["frame_ids"]
        for camera in truth.cameras:
            with zipfile.ZipFile(decoder / "image" / f"cam{camera}.zip") as archive:
                infos = archive.infolist()
                names = [i.filename for i in infos]
                expected = [f"cam{camera}/{f:06d}.avif" for f in frame_ids]
                if (subject, camera) == (dropped["subject"], dropped["camera"]):
                    expected.remove(f"cam{camera}/{dropped['frame_id']:06d}.avif")
                assert names == expected
                assert all(
                    i.compress_type == zipfile.ZIP_STORED and i.date_time == (1980, 1, 1, 0, 0, 0)
                    for i in infos
                )
                from PIL import Image

                image = Image.open(io.BytesIO(archive.read(names[0])))
                assert image.format == "AVIF" and image.size == (width, height)


def test_d2_avif_holds_linear_recorded_colour(world):
    """Decoded codes / 255 match M @ (true linear render) within the codec's error."""
    from PIL import Image

    from relightanyone.synth.d2_ava256 import even_lights

    truth = load_truth(world, "d2")
    subject = sorted(truth.splits)[0]
    camera = frontal_camera(truth)
    frame_id = truth.extra["captures"][subject]["frame_ids"][0]
    with zipfile.ZipFile(d2_capture(world, truth, subject) / "image" / f"cam{camera.name}.zip") as archive:
        decoded = np.asarray(
            Image.open(io.BytesIO(archive.read(f"cam{camera.name}/{frame_id:06d}.avif"))).convert("RGB")
        )
    # The subject is rebuilt from its answers (shape and maps) and rendered with the truth camera.
    template = make_template(micro_preset().template_segments)
    albedo = _read_exr(world / "answers" / "d2" / "subjects" / subject / "albedo.exr")
    spec = _read_exr(world / "answers" / "d2" / "subjects" / subject / "specular_intensity.exr")[..., 0]
    rough = _read_exr(world / "answers" / "d2" / "subjects" / subject / "roughness.exr")[..., 0]
    scene = Scene(
        subject_shape(world, "d2", subject),
        template.faces,
        template.uvs,
        template.face_uvs,
        albedo,
        spec,
        rough,
    )
    cam = SynthCamera(camera.name, camera.K, camera.w2c, camera.width, camera.height, camera.dist)
    result = render(scene, cam, even_lights(micro_preset().d2.lights))
    expected = np.einsum("ij,hwj->hwi", truth.colour_response[camera.name], result.image)
    inner = cv2.erode(result.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    mean_decoded = decoded[inner].mean(axis=0) / 255.0
    mean_expected = np.clip(expected[inner], 0, 1).mean(axis=0)
    assert np.allclose(mean_decoded, mean_expected, atol=0.02), (mean_decoded, mean_expected)
    # A colour cast per camera: the responses differ between cameras and no colour file is shipped.
    responses = np.stack(list(truth.colour_response.values()))
    assert np.ptp(responses[:, 0, 0] / responses[:, 2, 2]) > 0.01
    assert not list((world / "ava256").rglob("*colo*r*cal*"))


def _read_exr(path):
    from relightanyone.synth.envmap import read_exr

    return read_exr(path)


# ---------------------------------------------------------------------------------------------- D3


def test_d3_every_dng_reads_back_with_rawpy(world):
    import rawpy

    from relightanyone.synth.d3_stereo_rig import BLACK_LEVEL, WHITE_LEVEL

    width, height = micro_preset().d3.image_size
    paths = sorted((world / "stereo_rig").rglob("*.dng"))
    assert len(paths) == 8 + 8 * 2  # chart frames + one frame per camera and subject
    for path in paths:
        with rawpy.imread(str(path)) as raw:
            assert raw.raw_image_visible.shape == (height, width)
            assert raw.black_level_per_channel == [BLACK_LEVEL] * 4 and raw.white_level == WHITE_LEVEL
            assert raw.color_desc == b"RGBG" and raw.raw_pattern.tolist() == [[0, 1], [3, 2]]  # RGGB
            assert raw.raw_image_visible.max() <= WHITE_LEVEL and raw.raw_image_visible.min() >= 0


def test_d3_chart_is_detected_and_a_3x3_fit_undoes_the_camera_response(world):
    from relightanyone.synth.capture import srgb_encode, to_uint8
    from relightanyone.synth.d3_stereo_rig import chart_reference_linear_srgb, decode_dng

    truth = load_truth(world, "d3")
    reference = chart_reference_linear_srgb()
    for camera in truth.cameras:
        linear = decode_dng(world / "stereo_rig" / "calibration" / "colorchecker" / f"{camera}.dng")
        display = to_uint8(srgb_encode(linear / np.percentile(linear, 99.5)))
        detector = cv2.mcc.CCheckerDetector.create()
        detector.setColorChartType(cv2.mcc.MCC24)
        assert detector.process(cv2.cvtColor(display, cv2.COLOR_RGB2BGR), 1), f"{camera}: chart not detected"
        corners = np.array(detector.getBestColorChecker().getColorCharts()).reshape(24, 4, 2)
        measured = []
        for quad in corners:  # the middle of each patch, away from its blurred edges
            centre = quad.mean(axis=0)
            inner = (centre + 0.4 * (quad - centre)).astype(np.int32)
            mask = np.zeros(linear.shape[:2], np.uint8)
            cv2.fillConvexPoly(mask, inner, 1)
            measured.append(linear[mask.astype(bool)].mean(axis=0))
        measured = np.array(measured)
        # Fit reference ~ C @ measured (per patch) and compare C with the inverse of the true response,
        # up to the flash irradiance on the chart (a global scale the fit absorbs).
        C = np.linalg.lstsq(measured, reference, rcond=None)[0].T
        corrected = measured @ C.T
        assert np.abs(corrected - reference).max() < 0.04, camera
        true_inverse = np.linalg.inv(truth.colour_response[camera])
        ratio = C / true_inverse
        assert np.allclose(
            C / np.median(np.diag(ratio)), true_inverse, atol=0.08 * np.abs(true_inverse).max()
        ), camera


def test_d3_colmap_model_projects_where_the_renderer_drew_it(world):
    import pycolmap

    truth = load_truth(world, "d3")
    model = pycolmap.Reconstruction(str(world / "stereo_rig" / "calibration" / "sparse" / "0"))
    assert model.num_cameras() == 8 and model.num_images() == 8
    rig = json.loads((world / "stereo_rig" / "rig.json").read_text())
    assert len(rig["stereo_pairs"]) == 4
    camera = frontal_camera(truth)
    image = next(im for im in model.images.values() if im.name == f"{camera.name}.dng")
    colmap_camera = model.cameras[image.camera_id]
    assert colmap_camera.model.name == "OPENCV"
    subject = sorted(truth.splits)[0]
    vertex = nose_tip()
    pixel, drawn, incident, point = drawn_at(world, truth, subject, camera, vertex)
    world_point = truth.world_from_canonical[:3, :3] @ point + truth.world_from_canonical[:3, 3]
    in_camera = image.cam_from_world() * world_point
    uv_colmap = colmap_camera.img_from_cam(in_camera[None])[0]
    uv_opencv = np.asarray(uv_colmap) - 0.5  # COLMAP: the top-left pixel's centre is (0.5, 0.5)
    assert np.linalg.norm(uv_opencv - pixel) < 1.0
    assert drawn & incident


# ---------------------------------------------------------------------------------------------- D4


def test_d4_calibration_videos_and_colour_correction(world):
    import av
    import colour

    from relightanyone.synth.d4_nersemble import SEQUENCE, SERIALS

    truth = load_truth(world, "d4")
    width, height = micro_preset().d4.image_size
    for participant in truth.splits:
        folder = world / "nersemble" / participant
        params = json.loads((folder / "calibration" / "camera_params.json").read_text())
        assert list(params["world_2_cam"]) == list(SERIALS)
        assert np.array(params["intrinsics"]).shape == (3, 3)
        ccms = json.loads((folder / "calibration" / "color_calibration.json").read_text())
        assert set(ccms) == set(SERIALS)
        for serial in SERIALS:
            with av.open(str(folder / "sequences" / SEQUENCE / "images" / f"cam_{serial}.mp4")) as container:
                frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
            assert len(frames) == micro_preset().d4.frames and frames[0].shape == (height, width, 3)
            assert (folder / "sequences" / "BACKGROUND" / f"image_{serial}.jpg").is_file()
    # The release's correction (sRGB decode, CCM, encode) undoes the cast: a grey plate pixel turns neutral-ish
    # and matches the true linear colour times the CCM's inverse.
    camera = frontal_camera(truth)
    participant = sorted(truth.splits)[0]
    ccm = np.array(
        json.loads(
            (world / "nersemble" / participant / "calibration" / "color_calibration.json").read_text()
        )[camera.name]
    )
    assert np.allclose(ccm @ truth.colour_response[camera.name], np.eye(3), atol=1e-9)
    with av.open(
        str(world / "nersemble" / participant / "sequences" / SEQUENCE / "images" / f"cam_{camera.name}.mp4")
    ) as container:
        frame = next(container.decode(video=0)).to_ndarray(format="rgb24") / 255.0
    linear = colour.cctf_decoding(frame)
    corrected = linear @ ccm.T
    corner = corrected[:4, :4].reshape(-1, 3).mean(axis=0)  # the background plate, nearly white
    assert corner.min() > 0.2 and np.ptp(corner) / corner.mean() < 0.15


def test_d4_vertex_projects_where_the_renderer_drew_it(world):
    truth = load_truth(world, "d4")
    participant = sorted(truth.splits)[0]
    params = json.loads(
        (world / "nersemble" / participant / "calibration" / "camera_params.json").read_text()
    )
    camera = frontal_camera(truth)
    w2c = np.array(params["world_2_cam"][camera.name])
    K = np.array(params["intrinsics"])
    pose = truth.head_poses[(participant, 1)]
    pixel, drawn, incident, point = drawn_at(world, truth, participant, camera, nose_tip(), pose)
    world_point = truth.world_from_canonical @ np.append(point, 1.0)
    uvw = K @ (w2c @ world_point)[:3]
    assert np.linalg.norm(uvw[:2] / uvw[2] - pixel) < 1.0
    assert drawn & incident


# ---------------------------------------------------------------------------------------------- VHAP


@pytest.mark.parametrize("dataset", FLAT)
def test_vhap_export_reprojects_tracked_meshes(world, dataset):
    truth = load_truth(world, dataset)
    subject = sorted(truth.splits)[0]
    folder = world / "tracking" / dataset / subject
    transforms = json.loads((folder / "transforms.json").read_text())
    keys = sorted(f for (s, f) in truth.head_poses if s == subject)
    assert transforms["timestep_indices"] == list(range(len(keys)))
    assert len(transforms["frames"]) == len(keys) * len(truth.cameras)
    for split in ("train", "val", "test"):
        assert (folder / f"transforms_{split}.json").is_file()
    vertex = nose_tip()
    tracking_from_canonical = np.array(truth.extra["tracking_from_canonical"][subject])
    for t, key in enumerate(keys):
        mesh, faces, uvs, _ = read_obj(folder / "meshes" / f"{t:05d}.obj")
        expected = subject_shape(world, dataset, subject)
        motion = tracking_from_canonical @ truth.head_poses[(subject, key)]
        expected = expected @ motion[:3, :3].T + motion[:3, 3]
        error = np.linalg.norm(mesh - expected, axis=1)
        assert 0.0002 < error.mean() < 0.0015 and uvs is not None  # ~0.5 mm tracking noise
        frame = next(f for f in transforms["frames"] if f["timestep_index"] == t)
        c2w = np.array(frame["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV
        w2c = np.linalg.inv(c2w)
        K = np.array(
            [[frame["fl_x"], 0, frame["cx"]], [0, frame["fl_y"], frame["h"] - frame["cy"]], [0, 0, 1]]
        )
        camera = truth.cameras[frame["camera_id"]]
        in_cam = w2c[:3, :3] @ expected[vertex] + w2c[:3, 3]
        uv = (K @ in_cam)[:2] / in_cam[2]
        cam = SynthCamera(camera.name, camera.K, camera.w2c, camera.width, camera.height, np.zeros(5))
        canonical_point = subject_shape(world, dataset, subject)[vertex]
        pose = truth.head_poses[(subject, key)]
        truth_uv = cam.project((canonical_point @ pose[:3, :3].T + pose[:3, 3])[None])[0]
        assert np.linalg.norm(uv - truth_uv) < 1e-6
    # The tracking world is centred on the mean head position.
    head_positions = np.stack(
        [(tracking_from_canonical @ truth.head_poses[(subject, k)])[:3, 3] for k in keys]
    )
    assert np.allclose(head_positions.mean(axis=0), 0.0, atol=1e-9)


# ---------------------------------------------------------------------------------------------- answers


def test_answers_relit_images_follow_from_the_olat_answers(world):
    from relightanyone.synth.envmap import olat_relight_weights, read_exr

    description = json.loads((world / "world.json").read_text())
    lights = json.loads((world / "answers" / "answer_lights.json").read_text())
    assert len(lights["positions"]) == micro_preset().answer_lights
    splits = json.loads((world / "answers" / "splits.json").read_text())
    envmap_name = description["envmaps"][0]
    envmap = read_exr(world / "answers" / "envmaps" / f"{envmap_name}.exr")
    weights = olat_relight_weights(envmap, np.array(lights["positions"]), np.array(lights["intensities"]))
    for dataset in FLAT:
        truth = load_truth(world, dataset)
        held_out = [s for s, split in splits[dataset].items() if split == "test"]
        assert held_out and held_out == [s for s, split in truth.splits.items() if split == "test"]
        subject = held_out[0]
        for camera in truth.cameras:
            folder = world / "answers" / dataset / "olat" / subject / camera
            assert len(list(folder.glob("*.exr"))) == micro_preset().answer_lights
        camera = frontal_camera(truth).name
        olat = np.stack(
            [
                read_exr(p)
                for p in sorted((world / "answers" / dataset / "olat" / subject / camera).glob("*.exr"))
            ]
        )
        relit = read_exr(world / "answers" / dataset / "relit" / subject / camera / f"{envmap_name}.exr")
        assert olat.max() > 0 and relit.max() > 0
        assert np.allclose(
            np.einsum("lc,lhwc->hwc", weights, olat), relit, rtol=0.01, atol=1e-3 * relit.max()
        )
        for train_subject in (s for s, split in splits[dataset].items() if split == "train"):
            assert not (world / "answers" / dataset / "olat" / train_subject).exists()
