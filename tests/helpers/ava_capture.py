"""A small Ava-256-layout capture written from scratch (not with the synthetic world), for the rig tests.

The rig looks like the real one scaled down: a portrait sensor of the real 2668x4096 aspect (``SENSOR``,
1/16 of it by default), principal points off-centre the way the real rig's are (median (1482, 1710) px on
2668x4096), distortion, millimetres, K and T stored transposed, a head pose per frame. Images are a
downscale of the sensor by any factor, rounded per axis like the release (``sensor / factor``), and show
the posed template's silhouette on black. The VHAP-style tracking export (mesh mode) lives in a tracking
world of its own, so the ingest has to fit native -> tracker -> canonical.
"""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from relightanyone.render.camera import resize_intrinsics
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.template import make_template, write_obj, write_template
from relightanyone.synth.vhap import camera_entry

REAL_SENSOR = (2668, 4096)
REAL_PRINCIPAL_POINT = (1482.0, 1710.0)  # median of the real rig, sensor pixels
REAL_FOCAL = 10355.0  # sensor pixels
SENSOR = (167, 256)  # the real sensor / 16, so that even the full-sensor images stay tiny
SUBJECT = "AAA001"
FOLDER = f"20230405--1635--{SUBJECT}"
FRAMES = (10, 14)


@dataclass
class AvaCapture:
    """Where the capture is and what is true about it."""

    root: Path  # the Ava-256 source folder (holds the capture folder)
    tracking: Path  # holds <subject>/transforms.json
    template: Path
    cameras: list[str]
    K_sensor: dict[str, np.ndarray]  # (3, 3) per camera, sensor pixels
    w2c_head: dict[tuple[int, str], np.ndarray]  # (frame, camera) -> (4, 4) canonical metres -> camera
    image_size: tuple[int, int]

    def K_image(self, camera: str) -> np.ndarray:
        """(3, 3) K of the stored images: the sensor's resized per axis to the stored size."""
        sx = self.image_size[0] / self.sensor[0]
        sy = self.image_size[1] / self.sensor[1]
        return resize_intrinsics(self.K_sensor[camera], sx, sy)

    sensor: tuple[int, int] = SENSOR


def downscaled(size: tuple[int, int], factor: int) -> tuple[int, int]:
    """The stored size of a ``factor`` downscale: each axis rounded (166.75 -> 167)."""
    return tuple(max(1, int(round(s / factor))) for s in size)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle)
    return R


def _rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _silhouette(vertices: np.ndarray, faces: np.ndarray, K, w2c, dist, size) -> np.ndarray:
    """(H, W, 3) uint8: the mesh's silhouette in grey on black."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    rvec, _ = cv2.Rodrigues(R)
    uv, _ = cv2.projectPoints(vertices.reshape(-1, 1, 3), rvec, t, K, dist)
    uv = uv.reshape(-1, 2)
    image = np.zeros((size[1], size[0], 3), np.uint8)
    shift = 4  # sub-pixel vertex positions for fillPoly
    for face in faces:
        cv2.fillPoly(
            image, [np.round(uv[face] * (1 << shift)).astype(np.int32)], (150, 120, 100), shift=shift
        )
    return image


def write_ava_capture(
    folder: Path, factor: int = 1, cameras: int = 8, sensor: tuple[int, int] = SENSOR, seed: int = 0
) -> AvaCapture:
    """Write ``folder/ava256/<capture>/decoder/...``, ``folder/tracking/<subject>/`` and the template.

    ``factor``: downscale of the stored images from ``sensor`` (width, height).
    """
    rng = np.random.default_rng(seed)
    folder = Path(folder)
    template = make_template(12)
    write_template(folder / "template", template)
    scale = sensor[1] / REAL_SENSOR[1]
    names = [f"4009{k:02d}" for k in range(cameras)]
    # The capture room's world in mm: G (rigid, mm translation) <- room metres (the head at rest at 0).
    G = _rigid(_rotation(rng.normal(size=3), 0.7), rng.uniform(-800, 800, 3))
    tracker_from_room = _rigid(_rotation(rng.normal(size=3), 1.1), rng.uniform(-0.3, 0.3, 3))
    poses = {
        frame: _rigid(_rotation(rng.normal(size=3), np.radians(6.0 * k)), rng.uniform(-0.01, 0.01, 3))
        for k, frame in enumerate(FRAMES)
    }
    image_size = downscaled(sensor, factor)
    sx, sy = image_size[0] / sensor[0], image_size[1] / sensor[1]
    krt, K_sensor, w2c_head, room_cameras = [], {}, {}, {}
    for k, name in enumerate(names):
        azimuth = np.radians(-70 + 140 * k / max(cameras - 1, 1))
        eye = np.array([np.sin(azimuth), 0.15 * np.cos(3 * azimuth), np.cos(azimuth)]) * 1.2
        w2c_room = look_at_w2c(eye, np.zeros(3))
        jitter = rng.normal(0.0, 40.0, 2) * scale
        K = np.array(
            [
                [REAL_FOCAL * scale, 0.0, REAL_PRINCIPAL_POINT[0] * scale + jitter[0]],
                [0.0, REAL_FOCAL * scale, REAL_PRINCIPAL_POINT[1] * scale + jitter[1]],
                [0.0, 0.0, 1.0],
            ]
        )
        dist = np.array([-0.07, 0.04, -0.003, 0.003])
        w2c_mm = np.eye(4)
        w2c_mm[:3, :3] = w2c_room[:3, :3] @ G[:3, :3].T
        w2c_mm[:3, 3] = -w2c_mm[:3, :3] @ G[:3, 3] + 1000.0 * w2c_room[:3, 3]
        krt.append(
            {
                "cameraId": name,
                "projectionModel": "Pinhole",
                "distortionModel": "RadialAndTangential",
                "K": K.T.tolist(),
                "distortion": dist.tolist(),
                "T": w2c_mm.T.tolist(),
            }
        )
        K_sensor[name] = K
        room_cameras[name] = (w2c_room, dist)
    decoder = folder / "ava256" / FOLDER / "decoder"
    decoder.mkdir(parents=True)
    (decoder / "camera_calibration.json").write_text(json.dumps({"KRT": krt}))
    (decoder / "frame_list.csv").write_text(
        "seg_id,frame_id\n" + "".join(f"EXP_neutral_peak,{frame}\n" for frame in FRAMES)
    )
    (decoder / "head_pose").mkdir()
    with zipfile.ZipFile(decoder / "head_pose" / "head_pose.zip", "w") as archive:
        for frame, pose in poses.items():
            head_mm = np.hstack(
                [G[:3, :3] @ pose[:3, :3], (1000.0 * G[:3, :3] @ pose[:3, 3] + G[:3, 3])[:, None]]
            )
            archive.writestr(
                f"{frame:06d}.txt", "".join(" ".join(f"{v:.12g}" for v in row) + "\n" for row in head_mm)
            )
    (decoder / "image").mkdir()
    for name in names:
        w2c_room, dist = room_cameras[name]
        K_image = resize_intrinsics(K_sensor[name], sx, sy)
        with zipfile.ZipFile(decoder / "image" / f"cam{name}.zip", "w") as archive:
            for frame, pose in poses.items():
                w2c_head[(frame, name)] = w2c_room @ pose
                image = _silhouette(
                    template.vertices, template.faces, K_image, w2c_room @ pose, dist, image_size
                )
                buffer = io.BytesIO()
                Image.fromarray(image).save(buffer, format="AVIF", quality=90, speed=8)
                archive.writestr(f"cam{name}/{frame:06d}.avif", buffer.getvalue())
    _write_tracking(
        folder / "tracking" / SUBJECT,
        template,
        names,
        room_cameras,
        K_sensor,
        sensor,
        tracker_from_room,
        poses,
    )
    return AvaCapture(
        folder / "ava256",
        folder / "tracking",
        folder / "template" / "template.obj",
        names,
        K_sensor,
        w2c_head,
        image_size,
        sensor,
    )


def _write_tracking(
    folder, template, names, room_cameras, K_sensor, sensor, tracker_from_room, poses
) -> None:
    """A VHAP mesh-mode export: cameras (OpenGL c2w, flipped cy) and meshes in the tracker's world."""
    from types import SimpleNamespace

    frames = []
    for t, (frame, pose) in enumerate(poses.items()):
        motion = tracker_from_room @ pose
        write_obj(
            folder / "meshes" / f"{t:05d}.obj",
            template.vertices @ motion[:3, :3].T + motion[:3, 3],
            template.faces,
            template.uvs,
            template.face_uvs,
        )
        for ci, name in enumerate(names):
            camera = SimpleNamespace(
                K=K_sensor[name], w2c=room_cameras[name][0], width=sensor[0], height=sensor[1]
            )
            frames.append(
                {
                    "timestep_index": t,
                    "timestep_index_original": frame,
                    "timestep_id": f"{frame:06d}",
                    "camera_index": ci,
                    "camera_id": name,
                    **camera_entry(camera, tracker_from_room),
                    "file_path": f"images/{t:05d}_{ci:02d}.png",
                    "mesh_path": f"meshes/{t:05d}.obj",
                }
            )
    (folder / "transforms.json").write_text(
        json.dumps({"frames": frames, "timestep_indices": list(range(len(poses)))})
    )


def drop_image(capture: AvaCapture, camera: str, frame: int) -> None:
    """Remove one member from a camera's zip: a dropped frame as in the release."""
    path = next(capture.root.glob(f"*/decoder/image/cam{camera}.zip"))
    with zipfile.ZipFile(path) as archive:
        kept = [
            (i, archive.read(i)) for i in archive.infolist() if i.filename != f"cam{camera}/{frame:06d}.avif"
        ]
    with zipfile.ZipFile(path, "w") as archive:
        for info, data in kept:
            archive.writestr(info, data)
