"""Small, fully valid example content for tests, benchmarks and documentation.

``face_like_image`` draws a smooth, head-like linear image (an ellipse with shading, a specular highlight
and sensor noise over a black background, about half the frame covered); ``example_rows`` turns it into
image rows of a ring of cameras looking at the origin; ``write_example_dataset`` writes a complete small
OLAT dataset with meshes, lights and a quarantine entry.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from relightanyone.format.codecs import DEFAULT_IMAGE_ENCODING, encode_image, encode_mask
from relightanyone.format.schema import (
    DatasetInfo,
    ImageRow,
    LightRow,
    MeshRow,
    Provenance,
    QuarantineEntry,
    build_image_row,
)
from relightanyone.format.shards import ShardWriter
from relightanyone.render.camera import look_at_w2c


def face_like_image(height: int, width: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(image (H, W, 3) float32 linear in [0, ~1.5], mask (H, W) bool)``, deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    u = (x + 0.5) / width * 2.0 - 1.0 + rng.uniform(-0.05, 0.05)
    v = (y + 0.5) / height * 2.0 - 1.0
    radius_x, radius_y = 0.62, 0.82  # ellipse area pi*0.62*0.82/4 ~ 0.40 of the frame, plus the neck
    inside = (u / radius_x) ** 2 + (v / radius_y) ** 2
    mask = (inside <= 1.0) | ((np.abs(u) < 0.3) & (v > 0.5))
    normal_z = np.sqrt(np.clip(1.0 - inside, 0.0, 1.0))
    albedo = np.array([0.62, 0.42, 0.33], np.float32) * (1.0 + 0.1 * np.sin(6 * u + seed)[..., None])
    shading = 0.25 + 0.75 * normal_z * (0.6 + 0.4 * np.clip(-u + 0.3, 0, 1))
    highlight = 0.8 * np.exp(-(((u + 0.2) ** 2 + (v + 0.35) ** 2) / 0.01))
    image = albedo * shading[..., None] + highlight[..., None]
    image *= mask[..., None]
    image += rng.normal(0.0, 0.004, image.shape).astype(np.float32) * mask[..., None]
    return np.clip(image, 0.0, None).astype(np.float32), mask


def example_rows(
    dataset: str = "example",
    subjects: tuple[str, ...] = ("s000",),
    cameras: int = 2,
    patterns: tuple[str, ...] = ("full",),
    size: tuple[int, int] = (32, 24),
    encoding: str = DEFAULT_IMAGE_ENCODING,
    split: str = "train",
) -> list[ImageRow]:
    """Valid image rows for every subject x camera x pattern, frame 0; ``size`` is (height, width)."""
    height, width = size
    rows = []
    for s, subject in enumerate(subjects):
        for c in range(cameras):
            angle = 2 * np.pi * c / max(cameras, 1)
            w2c = look_at_w2c([np.sin(angle), 0.1, np.cos(angle)], np.zeros(3), [0.0, 1.0, 0.0])
            K = np.array([[1.2 * width, 0, (width - 1) / 2], [0, 1.2 * width, (height - 1) / 2], [0, 0, 1]])
            for p, pattern in enumerate(patterns):
                image, mask = face_like_image(height, width, seed=1000 * s + 10 * c + p)
                source = f"{subject}/cam{c:02d}/{pattern}.exr"
                rows.append(
                    build_image_row(
                        dataset=dataset,
                        subject=subject,
                        frame=0,
                        camera=f"cam{c:02d}",
                        pattern=pattern,
                        split=split,
                        K=K,
                        w2c=w2c,
                        image=encode_image(image, encoding),
                        image_encoding=encoding,
                        mask=encode_mask(mask),
                        width=width,
                        height=height,
                        source=source,
                        source_sha256=hashlib.sha256(source.encode()).hexdigest(),
                    )
                )
    return rows


def write_example_dataset(
    root: Path,
    name: str = "demo",
    subjects: tuple[str, ...] = ("s000", "s001", "s002"),
    task_order: tuple[str, ...] | None = None,
    max_shard_bytes: int = 1 << 30,
) -> Path:
    """A complete small OLAT dataset at ``root/name``: per subject 2 cameras x ("full", "olat-000"), a
    4-vertex mesh and one quarantined item; two rig lights. Tasks run in ``task_order`` (default: sorted)."""
    info = DatasetInfo(name, "olat", "flame", "2 OLAT lights", Provenance("FaceOLAT", "research"), "cfg-1")
    writer = ShardWriter(Path(root) / name, info, max_shard_bytes=max_shard_bytes)
    writer.begin()
    writer.write_lights(
        [LightRow(i, f"L{i}", (0.0, 1.0, float(i)), (1.0, 1.0, 1.0), f"olat-{i:03d}") for i in (1, 0)]
    )
    for subject in task_order or subjects:
        with writer.part(subject) as part:
            for row in reversed(example_rows(name, (subject,), cameras=2, patterns=("full", "olat-000"))):
                part.add(row)
            part.add_mesh(MeshRow(subject, 0, np.full((4, 3), subjects.index(subject), np.float32)))
            part.quarantine(
                QuarantineEntry(f"{subject}/cam09", f"{subject}/cam09.exr", "unreadable", "ingest")
            )
    writer.commit()
    return Path(root) / name
