"""Native calibration readers against hand-made known values, and the malformed-file errors."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from relightanyone.ingest.calibration import (
    CalibrationError,
    from_colmap,
    from_nersemble_params,
    from_transforms_json,
    read_krt_json,
    read_krt_text,
)
from relightanyone.ingest.metashape import read_metashape_xml
from relightanyone.render.camera import Cameras

ROT = cv2.Rodrigues(np.array([0.2, -0.4, 0.1]))[0]
T_M = np.array([0.05, -0.1, 1.2])  # metres
K_FULL = np.array([[1000.0, 0.0, 310.0], [0.0, 1010.0, 250.0], [0.0, 0.0, 1.0]])


def known_camera() -> Cameras:
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = ROT, T_M
    return Cameras.create(torch.tensor(K_FULL), torch.tensor(w2c), 640, 480)


def point_in_front(depth: float = 1.5, offset: tuple[float, float] = (0.1, -0.05)) -> np.ndarray:
    """A world point at camera-frame (offset * depth, depth) of the known camera, and its pixel."""
    cam = np.array([offset[0] * depth, offset[1] * depth, depth])
    return ROT.T @ (cam - T_M)


def expected_pixel(offset: tuple[float, float] = (0.1, -0.05)) -> np.ndarray:
    return np.array([1000.0 * offset[0] + 310.0, 1010.0 * offset[1] + 250.0])


# ---------------------------------------------------------------------------------------------- KRT
def write_krt_json(
    path: Path, K: np.ndarray, w2c_mm: np.ndarray, dist: list[float], camera_id: str = "400001"
) -> Path:
    entry = {
        "cameraId": camera_id,
        "projectionModel": "Pinhole",
        "distortionModel": "RadialAndTangential",
        "K": K.T.tolist(),
        "distortion": dist,
        "T": w2c_mm.T.tolist(),
    }
    path.write_text(json.dumps({"KRT": [entry]}))
    return path


def test_krt_json_transposes_and_converts_millimetres(tmp_path: Path) -> None:
    w2c_mm = np.eye(4)
    w2c_mm[:3, :3], w2c_mm[:3, 3] = ROT, T_M * 1000.0
    path = write_krt_json(tmp_path / "camera_calibration.json", K_FULL, w2c_mm, [0.0, 0.0, 0.0, 0.0])
    cams = read_krt_json(path, image_size=(640, 480))
    assert cams.names == ("400001",) and cams.dist.shape == (1, 5)
    np.testing.assert_allclose(cams.K[0].numpy(), K_FULL)
    np.testing.assert_allclose(cams.t[0].numpy(), T_M, atol=1e-12)
    uv, depth = cams.project(torch.tensor(point_in_front())[None])
    np.testing.assert_allclose(uv[0, 0].numpy(), expected_pixel(), atol=1e-9)
    assert float(depth[0, 0]) == pytest.approx(1.5)
    assert cams.width.tolist() == [640] and cams.height.tolist() == [480]


def test_krt_json_real_single_camera(real_fixtures: Path) -> None:
    cams = read_krt_json(real_fixtures / "ava-256" / "camera_calibration.json")
    raw = json.loads((real_fixtures / "ava-256" / "camera_calibration.json").read_text())["KRT"][0]
    assert cams.names == ("400940",)
    assert cams.width.tolist() == [2668] and cams.height.tolist() == [4096]
    assert float(cams.K[0, 0, 2]) == pytest.approx(raw["K"][2][0])  # cx was stored in the last row
    np.testing.assert_allclose(cams.t[0].numpy(), np.array(raw["T"])[3, :3] / 1000.0, atol=1e-12)
    np.testing.assert_allclose(cams.dist[0].numpy(), raw["distortion"] + [0.0])


def test_krt_text_parses_blocks(tmp_path: Path, real_fixtures: Path) -> None:
    rt = np.hstack([ROT, (T_M * 1000.0)[:, None]])
    block = ["cam7", *(" ".join(map(str, row)) for row in K_FULL), "0.1 0.01 0.001 0.002 0.0"]
    block += [" ".join(repr(float(v)) for v in row) for row in rt]
    path = tmp_path / "KRT"
    path.write_text("\n".join(block) + "\n\n" + "\n".join(["cam8", *block[1:]]) + "\n\n")
    cams = read_krt_text(path, image_size=(640, 480))
    assert cams.names == ("cam7", "cam8")
    np.testing.assert_allclose(cams.t[1].numpy(), T_M, atol=1e-12)
    np.testing.assert_allclose(cams.dist[0].numpy(), [0.1, 0.01, 0.001, 0.002, 0.0])
    legacy = read_krt_text(real_fixtures / "ava-256" / "KRT", image_size=(1334, 2048))
    assert len(legacy) == 38 and legacy.names[0] == "400069"
    assert float(legacy.K[0, 0, 0]) == pytest.approx(7724.681)
    np.testing.assert_allclose(legacy.t[0].numpy(), [-0.27026154, -0.2916677, 0.12137361], atol=1e-9)


# ---------------------------------------------------------------------------------------------- NeRSemble
def test_nersemble_shared_and_per_serial_intrinsics() -> None:
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = ROT, T_M
    params = {
        "world_2_cam": {"222200037": w2c.tolist(), "222200038": np.eye(4).tolist()},
        "intrinsics": K_FULL.tolist(),
    }
    cams = from_nersemble_params(params, image_size=(640, 480))
    assert cams.names == ("222200037", "222200038")
    uv, _ = cams[0].project(torch.tensor(point_in_front())[None])
    np.testing.assert_allclose(uv[0, 0].numpy(), expected_pixel(), atol=1e-9)
    per_serial = dict(
        params, intrinsics={"222200037": K_FULL.tolist(), "222200038": (K_FULL * [[2], [2], [1]]).tolist()}
    )
    cams2 = from_nersemble_params(per_serial)
    assert cams2.width.tolist() == [2200, 2200] and float(cams2.K[1, 0, 0]) == 2000.0


# ---------------------------------------------------------------------------------------------- transforms.json
def vhap_transforms(cams: Cameras, full_height: int, downsample: int) -> dict:
    """Write cameras the way VHAP exports them: OpenGL c2w, cy flipped with the full height, then K / n."""
    frames = []
    for b in range(len(cams)):
        c2w_gl = cams.c2w[b].numpy() @ np.diag([1.0, -1.0, -1.0, 1.0])
        K = cams.K[b].numpy().copy()
        K[1, 2] = full_height - K[1, 2]
        K[:2] /= downsample
        frames.append(
            {
                "camera_id": cams.names[b],
                "file_path": f"images/00000_{b:02d}.png",
                "transform_matrix": c2w_gl.tolist(),
                "fl_x": K[0, 0],
                "fl_y": K[1, 1],
                "cx": K[0, 2],
                "cy": K[1, 2],
                "w": int(cams.width[b]) // downsample,
                "h": full_height // downsample,
            }
        )
    return {"frames": frames + frames}  # every camera appears at two timesteps


def test_transforms_json_round_trips_opengl_c2w_and_flipped_cy() -> None:
    native = Cameras.cat(
        [known_camera(), known_camera()[0].transform_world(torch.eye(4, dtype=torch.float64))]
    )
    native = native.with_names(["a", "b"])
    data = vhap_transforms(native, 480, 1)
    cams = from_transforms_json(data, per="camera")
    assert cams.names == ("a", "b")
    torch.testing.assert_close(cams.w2c, native.w2c)
    torch.testing.assert_close(cams.K, native.K)
    per_frame = from_transforms_json(data)
    assert len(per_frame) == 4 and per_frame.names[0] == "images/00000_00.png"
    # With the downsample factor the half-pixel rule is restored: equal to resizing the native cameras.
    down = from_transforms_json(vhap_transforms(native, 480, 4), per="camera", vhap_downsample=4)
    torch.testing.assert_close(down.K, native.resize(0.25).K)
    points = torch.tensor(np.random.default_rng(0).normal(size=(30, 3)) * 0.1)
    torch.testing.assert_close(down.project(points)[0], native.resize(0.25).project(points)[0])


def test_transforms_json_refuses_a_camera_that_changes_between_timesteps() -> None:
    native = Cameras.cat(
        [known_camera(), known_camera()[0].transform_world(torch.eye(4, dtype=torch.float64))]
    ).with_names(["a", "b"])
    data = vhap_transforms(native, 480, 1)
    moved = copy.deepcopy(data["frames"][2])  # camera "a" at its second timestep
    moved["transform_matrix"][0][3] += 0.01
    data["frames"][2] = moved
    with pytest.raises(CalibrationError, match=r"frames\[2\].*camera a has different parameters"):
        from_transforms_json(data, per="camera")


# ---------------------------------------------------------------------------------------------- COLMAP
@pytest.mark.parametrize("binary", [True, False])
def test_colmap_models_match_colmap_projection(tmp_path: Path, binary: bool) -> None:
    import pycolmap

    models = {
        "SIMPLE_PINHOLE": [500.0, 320.5, 240.5],
        "PINHOLE": [500.0, 510.0, 320.5, 240.5],
        "SIMPLE_RADIAL": [500.0, 320.5, 240.5, 0.05],
        "RADIAL": [500.0, 320.5, 240.5, 0.05, -0.01],
        "OPENCV": [500.0, 510.0, 320.5, 240.5, 0.05, -0.01, 0.001, 0.002],
        "FULL_OPENCV": [500.0, 510.0, 320.5, 240.5, 0.05, -0.01, 0.001, 0.002, 0.003, 0.01, 0.002, 0.001],
    }
    rec = pycolmap.Reconstruction()
    poses = {}
    for camera_id, (model, params) in enumerate(models.items(), start=1):
        camera = pycolmap.Camera.create_from_model_name(camera_id, model, 500.0, 640, 480)
        camera.params = params
        rec.add_camera_with_trivial_rig(camera)
        pose = np.hstack([cv2.Rodrigues(np.array([0.1 * camera_id, 0.2, 0.0]))[0], [[0.1], [0.0], [2.0]]])
        poses[model] = pose
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{model}.png", camera_id=camera_id, image_id=camera_id),
            pycolmap.Rigid3d(pose),
        )
    (rec.write_binary if binary else rec.write_text)(str(tmp_path))
    cams = from_colmap(tmp_path)
    assert set(cams.names) == {f"{m}.png" for m in models}
    points = np.random.default_rng(1).normal(size=(20, 3)) * 0.3
    for b, name in enumerate(cams.names):
        model = name[:-4]
        cam_points = points @ poses[model][:, :3].T + poses[model][:, 3]
        expected = rec.camera(list(models).index(model) + 1).img_from_cam(cam_points) - 0.5
        uv, _ = cams[b].project(torch.tensor(points))
        np.testing.assert_allclose(uv[0].numpy(), expected, atol=1e-6)


# ---------------------------------------------------------------------------------------------- Metashape
METASHAPE_XML = """<?xml version="1.0" encoding="UTF-8"?>
<document version="2.0.0"><chunk label="Chunk 1">
  <sensors next_id="3">
    <sensor id="0" label="A" type="frame"><resolution width="640" height="480"/>
      <calibration type="frame" class="adjusted"><resolution width="640" height="480"/>
        <f>1000</f><cx>12.5</cx><cy>-7.25</cy><b1>3.5</b1><b2>0.75</b2>
        <k1>0.05</k1><k2>-0.02</k2><k3>0.01</k3><p1>0.002</p1><p2>-0.001</p2></calibration></sensor>
    <sensor id="1" label="B" type="frame"><resolution width="640" height="480"/></sensor>
    <sensor id="2" label="C" type="frame"><resolution width="640" height="480"/>
      <calibration type="frame" class="adjusted"><f>900</f></calibration></sensor>
  </sensors>
  <cameras next_id="3">
    <camera id="0" sensor_id="0" label="A"><transform>{transform}</transform></camera>
    <group id="0" label="G"><camera id="1" sensor_id="1" label="B"><transform>{transform}</transform></camera></group>
    <camera id="2" sensor_id="2" label="C"/>
  </cameras>
  <transform><rotation>{rotation}</rotation><translation>0.5 -0.25 2</translation><scale>{scale}</scale></transform>
  <reference>LOCAL_CS["Local CS",LOCAL_DATUM["Local Datum",0],UNIT["metre",1]]</reference>
</chunk></document>
"""


def metashape_pixel(x: float, y: float) -> np.ndarray:
    """Metashape's frame-camera equation for sensor A (manual, appendix C), shifted to integer pixel centres."""
    f, cx, cy, b1, b2, k1, k2, k3, p1, p2 = 1000, 12.5, -7.25, 3.5, 0.75, 0.05, -0.02, 0.01, 0.002, -0.001
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    yd = y * radial + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    return np.array([320 + cx + xd * (f + b1) + yd * b2, 240 + cy + yd * f]) - 0.5


def write_metashape(
    path: Path, transform: str | None = None, rotation: str | None = None, scale: float = 2.0
) -> Path:
    c2w = np.eye(4)
    c2w[:3, :3] = cv2.Rodrigues(np.array([0.3, 0.1, -0.2]))[0]
    c2w[:3, 3] = [0.1, 0.2, -0.3]
    chunk_R = cv2.Rodrigues(np.array([-0.1, 0.5, 0.2]))[0]
    path.write_text(
        METASHAPE_XML.format(
            transform=transform or " ".join(repr(float(v)) for v in c2w.ravel()),
            rotation=rotation or " ".join(repr(float(v)) for v in chunk_R.ravel()),
            scale=scale,
        )
    )
    return path


def test_metashape_projection_follows_the_metashape_camera_model(tmp_path: Path) -> None:
    rig = read_metashape_xml(write_metashape(tmp_path / "cams.xml"))
    assert rig.cameras.names == ("A",) and rig.chunk_scale == pytest.approx(2.0)
    assert rig.missing == {
        "B": "sensor B has no <calibration>",
        "C": "camera has no <transform> (not aligned)",
    }
    c2w = np.eye(4)
    c2w[:3, :3] = cv2.Rodrigues(np.array([0.3, 0.1, -0.2]))[0]
    c2w[:3, 3] = [0.1, 0.2, -0.3]
    chunk_S = np.eye(4)
    chunk_S[:3, :3] = 2.0 * cv2.Rodrigues(np.array([-0.1, 0.5, 0.2]))[0]
    chunk_S[:3, 3] = [0.5, -0.25, 2.0]
    for x, y, depth in [(0.0, 0.0, 0.7), (0.1, -0.05, 0.9), (-0.12, 0.08, 1.1)]:
        chunk_point = c2w @ np.array([x * depth, y * depth, depth, 1.0])
        world_point = (chunk_S @ chunk_point)[:3]
        uv, cam_depth = rig.cameras.project(torch.tensor(world_point)[None])
        np.testing.assert_allclose(uv[0, 0].numpy(), metashape_pixel(x, y), atol=1e-9)
        assert float(cam_depth[0, 0]) == pytest.approx(2.0 * depth)  # camera frames scale with the world


# ---------------------------------------------------------------------------------------------- malformed files
def krt_entry() -> dict:
    w2c_mm = np.eye(4)
    w2c_mm[:3, :3], w2c_mm[:3, 3] = ROT, T_M * 1000.0
    return {"cameraId": "400001", "K": K_FULL.T.tolist(), "distortion": [0.0] * 4, "T": w2c_mm.T.tolist()}


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda e: e.pop("K"), "KRT[0] (cameraId 400001).K"),
        (lambda e: e["T"][0].__setitem__(1, float("nan")), "KRT[0] (cameraId 400001).T"),
        (lambda e: e.__setitem__("T", np.diag([1.0, 1.0, 0.0, 1.0]).tolist()), "KRT[0] (cameraId 400001).T"),
        (lambda e: e.__setitem__("K", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), "KRT[0] (cameraId 400001).K"),
        (lambda e: e.__setitem__("distortion", [0.1]), "KRT[0] (cameraId 400001).distortion"),
    ],
)
def test_malformed_krt_json_names_file_and_field(tmp_path: Path, mutate, field: str) -> None:
    entry = krt_entry()
    mutate(entry)
    path = tmp_path / "bad_calibration.json"
    path.write_text(json.dumps({"KRT": [entry]}))
    with pytest.raises(CalibrationError) as info:
        read_krt_json(path)
    assert str(path) in str(info.value) and field in str(info.value) and info.value.field == field


def test_malformed_files_of_every_format(tmp_path: Path) -> None:
    ok = write_metashape(tmp_path / "ok.xml")
    nan_xml = tmp_path / "nan.xml"
    nan_xml.write_text(ok.read_text().replace("<f>1000</f>", "<f>nan</f>"))
    with pytest.raises(CalibrationError, match=r"nan\.xml.*sensor\[A\]\.calibration\.f.*NaN"):
        read_metashape_xml(nan_xml)
    singular = write_metashape(tmp_path / "singular.xml", rotation="1 0 0 0 1 0 0 0 0")
    with pytest.raises(CalibrationError, match=r"singular\.xml.*chunk/transform\.rotation.*orthonormal"):
        read_metashape_xml(singular)
    short = write_metashape(tmp_path / "short.xml", transform="1 0 0 0 1 0 0 0 1")
    with pytest.raises(CalibrationError, match=r"short\.xml.*camera\[A\]/transform.*expected 16"):
        read_metashape_xml(short)

    params = tmp_path / "camera_params.json"
    params.write_text(json.dumps({"world_2_cam": {"1": np.eye(4).tolist()}}))
    with pytest.raises(CalibrationError, match=r"camera_params\.json.*'intrinsics'.*missing"):
        from_nersemble_params(params)
    params.write_text(json.dumps({"world_2_cam": {"1": np.eye(3).tolist()}, "intrinsics": K_FULL.tolist()}))
    with pytest.raises(CalibrationError, match=r"world_2_cam\.1.*shape"):
        from_nersemble_params(params)

    transforms = tmp_path / "transforms.json"
    transforms.write_text(json.dumps({"frames": [{"fl_x": 1.0, "cx": 1.0, "cy": 1.0, "w": 2, "h": 2}]}))
    with pytest.raises(CalibrationError, match=r"transforms\.json.*frames\[0\]\.transform_matrix.*missing"):
        from_transforms_json(transforms)

    krt = tmp_path / "KRT"
    krt.write_text("400001\n1 0 0\n0 1 0\n0 0 1\n0 0 0 0 0\n1 0 0 0\n0 1 0 0\n\n")
    with pytest.raises(CalibrationError, match=r"KRT.*camera 400001.*incomplete"):
        read_krt_text(krt, image_size=(10, 10))
    with pytest.raises(CalibrationError, match="file not found"):
        read_krt_json(tmp_path / "absent.json")
