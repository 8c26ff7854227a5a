"""A tiny normalized world for stage-1 tests: sphere-headed subjects seen by a ring of cameras.

Each dataset gets ``template.obj`` (a UV sphere with a seam, radius 0.1 m), tracked meshes (the sphere
scaled per subject) and full-on images: the projected sphere, Lambert-shaded, coloured by the subject's
albedo times the dataset's colour cast, over a grey background the mask excludes.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from relightanyone.format.codecs import encode_image, encode_mask
from relightanyone.format.schema import DatasetInfo, MeshRow, Provenance, build_image_row, fingerprint_config
from relightanyone.format.shards import ShardWriter
from relightanyone.render.camera import look_at_w2c

RADIUS = 0.1


def sphere_obj(rings: int = 8, segments: int = 12) -> tuple[np.ndarray, str]:
    """(vertices (V, 3), OBJ text) of a UV sphere; the seam at u = 0/1 duplicates texture coordinates."""
    vertices = [(0.0, RADIUS, 0.0)]
    for ring in range(1, rings):
        theta = np.pi * ring / rings
        for segment in range(segments):
            phi = 2 * np.pi * segment / segments
            vertices.append(
                (
                    RADIUS * np.sin(theta) * np.sin(phi),
                    RADIUS * np.cos(theta),
                    RADIUS * np.sin(theta) * np.cos(phi),
                )
            )
    vertices.append((0.0, -RADIUS, 0.0))
    bottom = len(vertices) - 1

    def vid(ring: int, segment: int) -> int:  # 1..rings-1 rings
        return 1 + (ring - 1) * segments + segment % segments

    uvs, faces = [], []

    def uv(u: float, v: float) -> int:
        uvs.append((u, v))
        return len(uvs) - 1

    for segment in range(segments):
        u0, u1 = segment / segments, (segment + 1) / segments
        for ring in range(rings):
            v0, v1 = 1 - ring / rings, 1 - (ring + 1) / rings
            if ring == 0:
                faces.append(
                    (
                        (0, uv((u0 + u1) / 2, v0)),
                        (vid(1, segment), uv(u0, v1)),
                        (vid(1, segment + 1), uv(u1, v1)),
                    )
                )
            elif ring == rings - 1:
                faces.append(
                    (
                        (vid(ring, segment), uv(u0, v0)),
                        (bottom, uv((u0 + u1) / 2, v1)),
                        (vid(ring, segment + 1), uv(u1, v0)),
                    )
                )
            else:
                a, b = (vid(ring, segment), uv(u0, v0)), (vid(ring, segment + 1), uv(u1, v0))
                c, d = (vid(ring + 1, segment), uv(u0, v1)), (vid(ring + 1, segment + 1), uv(u1, v1))
                faces.append((a, c, d))
                faces.append((a, d, b))
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uvs]
    lines += ["f " + " ".join(f"{v + 1}/{t + 1}" for v, t in face) for face in faces]
    return np.asarray(vertices, dtype=np.float64), "\n".join(lines) + "\n"


def render_sphere(scale: float, albedo: np.ndarray, K: np.ndarray, w2c: np.ndarray, size: int):
    """Ray-cast the sphere of radius RADIUS·scale at the origin: (image (H, W, 3), mask (H, W))."""
    c2w = np.linalg.inv(w2c)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    directions = (
        np.stack([(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1], np.ones_like(x)], -1) @ c2w[:3, :3].T
    )
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    origin = c2w[:3, 3]
    b = directions @ origin
    disc = b**2 - (origin @ origin - (RADIUS * scale) ** 2)
    mask = disc > 0
    t = -b - np.sqrt(np.clip(disc, 0, None))
    normals = (origin + t[..., None] * directions) / (RADIUS * scale)
    shade = 0.3 + 0.7 * np.clip(normals @ np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 0, 1)
    image = np.where(mask[..., None], albedo * shade[..., None], 0.2).astype(np.float32)
    return image, mask


def write_dataset(
    root: Path,
    name: str,
    subjects: int = 2,
    cameras: int = 4,
    size: int = 32,
    cast: np.ndarray | None = None,
    seed: int = 0,
) -> Path:
    """Write one normalized dataset under ``root/name`` and return its folder."""
    rng = np.random.default_rng(seed)
    cast = np.eye(3) if cast is None else np.asarray(cast)
    template_vertices, obj_text = sphere_obj()
    dataset_dir = root / name
    info = DatasetInfo(
        name=name,
        kind="flat",
        template_mesh_id="sphere",
        lighting="full-on",
        provenance=Provenance(source_dataset="stage1 test sphere world", licence="CC0"),
        config_fingerprint=fingerprint_config({"name": name, "seed": seed}),
    )
    writer = ShardWriter(dataset_dir, info)
    writer.begin()
    focal = 2.2 * size
    K = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1.0]])
    for s in range(subjects):
        subject = f"s{s:02d}"
        scale = 1.0 + 0.1 * s
        albedo = cast @ rng.uniform(0.3, 0.8, 3)
        with writer.part(subject) as part:
            part.add_mesh(
                MeshRow(subject=subject, frame=0, vertices=(template_vertices * scale).astype(np.float32))
            )
            for c in range(cameras):
                angle = 2 * np.pi * c / cameras
                w2c = look_at_w2c(
                    0.5 * np.array([np.sin(angle), 0.2, np.cos(angle)]), np.zeros(3), [0.0, 1.0, 0.0]
                )
                image, mask = render_sphere(scale, albedo, K, w2c, size)
                source = f"{subject}/cam{c:02d}.exr"
                part.add(
                    build_image_row(
                        dataset=name,
                        subject=subject,
                        frame=0,
                        camera=f"cam{c:02d}",
                        pattern="full",
                        split="train",
                        K=K,
                        w2c=w2c,
                        image=encode_image(image),
                        image_encoding="raw-f16",
                        mask=encode_mask(mask),
                        width=size,
                        height=size,
                        source=source,
                        source_sha256=hashlib.sha256(source.encode()).hexdigest(),
                    )
                )
    writer.commit()
    (dataset_dir / "template.obj").write_text(obj_text)
    return dataset_dir


def tiny_stage1_preset(**changes):
    """A stage-1 preset sized for tests: UV 16², 32² crops, small decoders, a learning rate that shows
    progress within a few iterations."""
    from relightanyone.model.networks.presets import get_preset

    settings = dict(
        uv_size=16,
        z_id_dim=8,
        z_l_dim=4,
        start_channels=16,
        min_channels=8,
        mesh_hidden=16,
        crop_size=32,
        batch_size=2,
        iterations=8,
        offset_anneal_iterations=4,
        warmup_iterations=6,
        checkpoint_every=4,
        log_every=2,
        image_every=4,
        held_out_cameras=1,
        learning_rate=1e-2,
    )
    settings.update(changes)
    return get_preset("tiny").replace(**settings)


def train_script(data: list[Path], out: Path, evaluate: bool = False, **preset_changes) -> str:
    """Python source that trains a tiny stage-1 run; for subprocesses (SIGKILL, torchrun)."""
    return (
        "import sys; from pathlib import Path\n"
        f"sys.path.insert(0, {str(Path(__file__).parents[1])!r})\n"
        "from helpers.stage1_world import tiny_stage1_preset\n"
        "from relightanyone.model.train.stage1 import Stage1Config, train_stage1\n"
        f"preset = tiny_stage1_preset(**{preset_changes!r})\n"
        f"train_stage1(Stage1Config([Path(p) for p in {[str(d) for d in data]!r}], Path({str(out)!r}), preset, "
        f"progress=False, evaluate={evaluate!r}))\n"
    )
