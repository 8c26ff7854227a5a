"""VHAP-style tracking export of a synthetic dataset (VHAP's NeRF-style export, mesh mode).

For every subject of a dataset it writes ``tracking/<dataset>/<subject>/``::

    transforms.json, transforms_train.json, transforms_val.json, transforms_test.json
    canonical.obj            the tracked shape in the unposed (canonical) head frame
    meshes/{t:05d}.obj       per-timestep tracked mesh in the tracking world, template topology and UVs

The tracking world is built from the dataset's native world the way VHAP builds it: converted to metres,
rotated so that the mean camera axes line up with the world axes (OpenGL: mean camera looks along -z,
y up; ``align_cameras_to_axes``), then translated so that the mean head position is the origin
(``relocate_flame_meshes``). Cameras are camera-to-world in OpenGL axes; ``cy`` is flipped (``h - cy``)
as VHAP does; intrinsics are in pixels of the native images. Meshes carry Gaussian tracking noise.
The exact similarity ``tracking world <- canonical`` of every subject is returned for the answers.
Images and foreground masks are not exported (the native dataset holds them); ``file_path`` and
``fg_mask_path`` keep VHAP's names so frames can be paired by (timestep, camera).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from relightanyone.synth.template import HeadTemplate, write_obj
from relightanyone.synth.truth import DatasetTruth

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
TRAIN_FRACTION = 0.7
VAL_CAMERA_INDEX = 8  # NeRSemble's frontal camera; VHAP falls back to the last camera


def gram_schmidt_columns(matrix: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal basis from the columns of ``matrix``, first column kept in direction."""
    basis = np.zeros((3, 3))
    for k in range(3):
        column = matrix[:, k] - basis[:, :k] @ (basis[:, :k].T @ matrix[:, k])
        basis[:, k] = column / np.linalg.norm(column)
    return basis


def metric_native_from_canonical(world_from_canonical: np.ndarray) -> np.ndarray:
    """(4, 4) rigid: the native world expressed in metres <- canonical metres."""
    scale = np.cbrt(np.linalg.det(world_from_canonical[:3, :3]))
    return np.diag([1.0 / scale, 1.0 / scale, 1.0 / scale, 1.0]) @ world_from_canonical


def tracking_from_canonical(truth: DatasetTruth, head_poses: list[np.ndarray]) -> np.ndarray:
    """(4, 4) rigid transform of one subject's tracking world <- canonical space.

    head_poses: that subject's per-timestep canonical head motions (4, 4).
    """
    metric = metric_native_from_canonical(truth.world_from_canonical)
    c2w_rotations = np.stack([(metric @ np.linalg.inv(cam.w2c))[:3, :3] for cam in truth.cameras.values()])
    bases_c2w = gram_schmidt_columns(c2w_rotations.mean(axis=0))
    bases_c2w[:, [1, 2]] *= -1.0  # the OpenGL target convention of align_cameras_to_axes
    align = np.eye(4)
    align[:3, :3] = bases_c2w.T
    aligned = align @ metric
    head_positions = np.stack([(aligned @ pose)[:3, 3] for pose in head_poses])
    recentre = np.eye(4)
    recentre[:3, 3] = -head_positions.mean(axis=0)
    return recentre @ aligned


def camera_entry(truth_camera, tracking_from_canon: np.ndarray) -> dict:
    """Per-camera fields of a transforms.json frame (intrinsics, OpenGL c2w in the tracking world)."""
    K, width, height = np.asarray(truth_camera.K), int(truth_camera.width), int(truth_camera.height)
    c2w = tracking_from_canon @ np.linalg.inv(truth_camera.w2c) @ OPENCV_TO_OPENGL
    fl_x, fl_y = float(K[0, 0]), float(K[1, 1])
    return {
        "cx": float(K[0, 2]),
        "cy": float(height - K[1, 2]),
        "fl_x": fl_x,
        "fl_y": fl_y,
        "h": height,
        "w": width,
        "camera_angle_x": 2.0 * math.atan(width / (2.0 * fl_x)),
        "camera_angle_y": 2.0 * math.atan(height / (2.0 * fl_y)),
        "transform_matrix": c2w.tolist(),
    }


def transforms_document(frames: list[dict], timesteps: list[int], camera_count: int) -> dict:
    """The whole transforms.json: frames plus VHAP's top-level copies of the last frame's intrinsics."""
    document = {"frames": frames}
    if frames:
        for key in ("cx", "cy", "fl_x", "fl_y", "h", "w", "camera_angle_x", "camera_angle_y"):
            document[key] = frames[-1][key]
    document["timestep_indices"] = timesteps
    document["camera_indices"] = list(range(camera_count))
    return document


def split_frames(frames: list[dict], timestep_count: int, camera_count: int) -> dict[str, list[dict]]:
    """VHAP's split: the first ceil(0.7 T) timesteps are train/val (val = camera 8 or the last), the rest test."""
    cut = math.ceil(TRAIN_FRACTION * timestep_count)
    val_camera = VAL_CAMERA_INDEX if camera_count > VAL_CAMERA_INDEX else camera_count - 1
    early = [f for f in frames if f["timestep_index"] < cut]
    return {
        "train": [f for f in early if f["camera_index"] != val_camera],
        "val": [f for f in early if f["camera_index"] == val_camera],
        "test": [f for f in frames if f["timestep_index"] >= cut],
    }


def export_subject(
    folder: Path,
    truth: DatasetTruth,
    template: HeadTemplate,
    subject,
    rng: np.random.Generator,
    noise_m: float,
) -> np.ndarray:
    """Write one subject's tracking folder; returns its (4, 4) tracking world <- canonical transform."""
    keys = sorted(frame for (name, frame) in truth.head_poses if name == subject.name)
    poses = [truth.head_poses[(subject.name, frame)] for frame in keys] if keys else [np.eye(4)]
    keys = keys or [0]
    tracking = tracking_from_canonical(truth, poses)
    cameras = list(truth.cameras.values())
    per_camera = [camera_entry(cam, tracking) for cam in cameras]
    frames: list[dict] = []
    canonical = np.asarray(subject.vertices, dtype=np.float64)
    write_obj(
        folder / "canonical.obj",
        canonical + rng.normal(0.0, noise_m, canonical.shape),
        template.faces,
        template.uvs,
        template.face_uvs,
    )
    for t, (frame_key, pose) in enumerate(zip(keys, poses, strict=True)):
        motion = tracking @ pose
        posed = canonical @ motion[:3, :3].T + motion[:3, 3]
        write_obj(
            folder / "meshes" / f"{t:05d}.obj",
            posed + rng.normal(0.0, noise_m, posed.shape),
            template.faces,
            template.uvs,
            template.face_uvs,
        )
        for ci, cam in enumerate(cameras):
            frames.append(
                {
                    "timestep_index": t,
                    "timestep_index_original": int(frame_key),
                    "timestep_id": f"{int(frame_key):06d}",
                    "camera_index": ci,
                    "camera_id": cam.name,
                    **per_camera[ci],
                    "file_path": f"images/{t:05d}_{ci:02d}.png",
                    "fg_mask_path": f"fg_masks/{t:05d}_{ci:02d}.png",
                    "mesh_path": f"meshes/{t:05d}.obj",
                }
            )
    timesteps = list(range(len(keys)))
    (folder / "transforms.json").write_text(
        json.dumps(transforms_document(frames, timesteps, len(cameras)), indent=2)
    )
    for split, subset in split_frames(frames, len(keys), len(cameras)).items():
        split_timesteps = sorted({f["timestep_index"] for f in subset})
        (folder / f"transforms_{split}.json").write_text(
            json.dumps(transforms_document(subset, split_timesteps, len(cameras)), indent=2)
        )
    return tracking


def export_tracking(
    out_root: Path,
    truth: DatasetTruth,
    template: HeadTemplate,
    subjects: list,
    rng: np.random.Generator,
    noise_m: float = 0.0005,
) -> dict[str, list]:
    """Write ``out_root/tracking/<dataset>/<subject>/`` for every subject; returns subject -> (4, 4) list
    of the tracking world <- canonical similarity (to be stored in the dataset's truth.extra)."""
    folder = Path(out_root) / "tracking" / truth.dataset
    transforms = {}
    for subject in subjects:
        tracking = export_subject(folder / subject.name, truth, template, subject, rng, noise_m)
        transforms[subject.name] = tracking.tolist()
    return transforms
