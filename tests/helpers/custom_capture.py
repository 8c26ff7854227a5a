"""Small hand-made custom captures for the ingest tests: a procedural template seen by four cameras over
noise images, so that nothing needs the synthetic world's renderer."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from relightanyone.ingest import custom
from relightanyone.ingest.records import AdapterOptions
from relightanyone.ingest.runner import IngestSummary, ingest_dataset
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.template import make_template, write_obj, write_template

CAMERA_NAMES = ("c0", "c1", "c2", "c3")
SIZE = (96, 128)  # width, height


def make_capture(root: Path, subjects=("s1", "s2"), frames=(0, 1)) -> Path:
    """A custom capture in metres: template.obj + neck mask at the root, 4 cameras, noise PNG images."""
    template = make_template(12)
    write_template(root, template)
    width, height = SIZE
    focal = 260.0
    cameras = {}
    for k, name in enumerate(CAMERA_NAMES):
        angle = np.radians(-30 + 20 * k)
        eye = np.array([np.sin(angle), 0.05, np.cos(angle)]) * 0.9
        cameras[name] = {
            "K": [[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]],
            "dist": [0.01, 0.0, 0.0, 0.0, 0.0],
            "w2c": look_at_w2c(eye, np.zeros(3)).tolist(),
            "width": width,
            "height": height,
        }
    (root / "cameras.json").write_text(json.dumps({"units": "m", "encoding": "srgb", "cameras": cameras}))
    rng = np.random.default_rng(0)
    for subject in subjects:
        for frame in frames:
            folder = root / "images" / subject / f"{frame:06d}"
            folder.mkdir(parents=True)
            for name in CAMERA_NAMES:
                cv2.imwrite(
                    str(folder / f"{name}.png"), rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
                )
            shift = np.array([0.0, 0.002 * frame, 0.0])
            write_obj(
                root / "meshes" / subject / f"{frame:06d}.obj", template.vertices + shift, template.faces
            )
    return root


def ingest(capture: Path, out: Path, **kwargs) -> IngestSummary:
    """Ingest a capture of :func:`make_capture` into ``out/custom`` (tiny preset, no progress bars)."""
    plan = custom.plan(capture, AdapterOptions())
    return ingest_dataset(
        plan, None, out, "tiny", progress=False, template=capture / "template.obj", **kwargs
    )


def dataset_bytes(path: Path) -> dict[str, bytes]:
    """File name -> bytes of every file directly in a dataset folder."""
    return {p.name: p.read_bytes() for p in sorted(path.iterdir()) if p.is_file()}
