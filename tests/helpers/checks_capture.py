"""A custom capture whose images show the head: the tracked mesh drawn over a black studio background,
seen by five cameras placed unevenly around it (so that no two views look alike), two frames with
different head poses. The capture's world is the studio's: z up, origin on the floor, not at the head.
The convention-check tests mutate it the way users get captures wrong, and run the command line on it
(:func:`ingest_custom`, :func:`quarantine`)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

from relightanyone.align.geometry import similarity, transform_points
from relightanyone.cli import cli
from relightanyone.ingest.steps import MeshSilhouette
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.template import make_template, write_obj, write_template

SIZE = (96, 128)  # width, height
HEAD_CENTRE = np.array([0.05, 1.55, 0.2])  # where the head is, in a y-up frame on the studio's floor
# The studio's world: z up, turned 25 degrees about it (cameras and meshes are written in it).
_TURN, _UP = np.radians(25.0), np.radians(90.0)
STUDIO_FROM_ROOM = similarity(
    1.0,
    np.array([[np.cos(_TURN), -np.sin(_TURN), 0], [np.sin(_TURN), np.cos(_TURN), 0], [0, 0, 1]])
    @ np.array([[1, 0, 0], [0, np.cos(_UP), -np.sin(_UP)], [0, np.sin(_UP), np.cos(_UP)]]),
)
# name -> (azimuth deg, height m, distance m, focal px, principal point shift px)
RIG = {
    "c0": (-55.0, 0.10, 0.85, 250.0, (-6.0, 4.0)),
    "c1": (-20.0, -0.05, 1.00, 300.0, (3.0, -8.0)),
    "c2": (5.0, 0.25, 0.90, 240.0, (0.0, 6.0)),
    "c3": (35.0, 0.00, 1.10, 330.0, (5.0, 0.0)),
    "c4": (70.0, -0.15, 0.80, 230.0, (-4.0, -5.0)),
}


def head_pose(frame: int) -> np.ndarray:
    """``(4, 4)`` the head's pose in the capture's world at ``frame``: a few degrees and millimetres apart."""
    angle = np.radians(3.0 * frame)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    return STUDIO_FROM_ROOM @ similarity(1.0, R, HEAD_CENTRE + [0.004 * frame, 0.002 * frame, 0.0])


def rig_cameras() -> dict[str, dict]:
    """``cameras.json`` entries of :data:`RIG` (metres, OpenCV axes)."""
    width, height = SIZE
    cameras = {}
    for name, (azimuth, up, distance, focal, (dx, dy)) in RIG.items():
        a = np.radians(azimuth)
        eye = HEAD_CENTRE + [np.sin(a) * distance, up, np.cos(a) * distance]
        cameras[name] = {
            "K": [[focal, 0, (width - 1) / 2 + dx], [0, focal, (height - 1) / 2 + dy], [0, 0, 1]],
            "w2c": (
                look_at_w2c(eye, HEAD_CENTRE + [0.0, 0.02, 0.0]) @ np.linalg.inv(STUDIO_FROM_ROOM)
            ).tolist(),
            "width": width,
            "height": height,
        }
    return cameras


def render(vertices: np.ndarray, faces: np.ndarray, camera: dict, rng: np.random.Generator) -> np.ndarray:
    """``(H, W, 3)`` uint8: the mesh (neck included) as textured skin over black."""
    mask = MeshSilhouette(vertices, faces).mask(np.array(camera["K"]), np.array(camera["w2c"]), SIZE)
    skin = np.array([150, 110, 90]) + rng.integers(-40, 40, (SIZE[1], SIZE[0], 3))
    return (skin * mask[..., None]).clip(0, 255).astype(np.uint8)


def make_rendered_capture(root: Path, subject: str = "s1", frames=(0, 1, 2)) -> Path:
    """Write the capture under ``root``: template.obj + neck mask, cameras.json, rendered PNGs, meshes."""
    template = make_template(12)
    write_template(root, template)
    cameras = rig_cameras()
    (root / "cameras.json").write_text(json.dumps({"units": "m", "encoding": "srgb", "cameras": cameras}))
    rng = np.random.default_rng(0)
    for frame in frames:
        posed = transform_points(head_pose(frame), template.vertices)
        folder = root / "images" / subject / f"{frame:06d}"
        folder.mkdir(parents=True)
        for name, camera in cameras.items():
            rgb = render(posed, template.faces, camera, rng)
            cv2.imwrite(str(folder / f"{name}.png"), rgb[..., ::-1])  # OpenCV writes BGR arrays
        write_obj(root / "meshes" / subject / f"{frame:06d}.obj", posed, template.faces)
    return root


def run(*args: str):
    return CliRunner().invoke(cli, [str(a) for a in args])


def ingest_custom(capture: Path, out: Path, *extra: str):
    return run("ingest", "custom", capture, "--out", out, "--preset", "tiny", *extra)


def quarantine(out: Path) -> list[dict]:
    path = out / "custom" / "quarantine.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []


def other_pose_mesh(capture: Path) -> None:
    """Frame 1 gets the mesh of a head pose 8 degrees and 13 mm away from what its images show."""
    template = make_template(12)
    angle = np.radians(8.0)
    tilt = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    wrong = head_pose(1) @ similarity(1.0, tilt, [0.013, 0.0, 0.0])
    write_obj(
        capture / "meshes" / "s1" / "000001.obj", transform_points(wrong, template.vertices), template.faces
    )
