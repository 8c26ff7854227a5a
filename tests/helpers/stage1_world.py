"""A tiny normalized world for stage-1 tests: sphere-headed subjects seen by a ring of cameras.

Each dataset gets ``template.obj`` (a UV sphere with a seam, radius 0.1 m), tracked meshes (the sphere
scaled per subject) and full-on images: the projected sphere, Lambert-shaded, coloured by the subject's
albedo times the dataset's colour cast, over a grey background the mask excludes.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from helpers.kill_handshake import IMPORT_HELPERS
from relightanyone.format.codecs import encode_image, encode_mask
from relightanyone.format.schema import (
    DatasetInfo,
    ImageRow,
    MeshRow,
    Provenance,
    build_image_row,
    fingerprint_config,
)
from relightanyone.format.shards import ShardWriter
from relightanyone.model.networks.presets import get_preset
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


def sphere_image_row(
    dataset: str,
    subject: str,
    camera: str,
    pattern: str,
    split: str,
    K: np.ndarray,
    w2c: np.ndarray,
    image: np.ndarray,
    mask: np.ndarray,
    source: str,
) -> ImageRow:
    """The normalized row of one rendered view of frame 0: ``image`` (H, W, 3) linear float stored as
    raw-f16, ``mask`` (H, W) bool; ``source`` is a made-up native path (its sha256 is of the path)."""
    return build_image_row(
        dataset=dataset,
        subject=subject,
        frame=0,
        camera=camera,
        pattern=pattern,
        split=split,
        K=K,
        w2c=w2c,
        image=encode_image(image),
        image_encoding="raw-f16",
        mask=encode_mask(mask),
        width=image.shape[1],
        height=image.shape[0],
        source=source,
        source_sha256=hashlib.sha256(source.encode()).hexdigest(),
    )


def sphere_mesh(subject: str, scale: float = 1.0) -> MeshRow:
    """The tracked mesh of a subject's frame 0: the template sphere scaled by ``scale``."""
    vertices, _ = sphere_obj()
    return MeshRow(subject=subject, frame=0, vertices=(vertices * scale).astype(np.float32))


@contextmanager
def sphere_dataset(
    root: Path, name: str, kind: str, lighting: str, source_dataset: str, fingerprint: dict
) -> Iterator[ShardWriter]:
    """Write the normalized dataset ``root/name`` of sphere subjects (template "sphere", CC0): yields its
    begun ShardWriter; when the block ends, commits it and writes the sphere's ``template.obj`` beside it."""
    info = DatasetInfo(
        name=name,
        kind=kind,
        template_mesh_id="sphere",
        lighting=lighting,
        provenance=Provenance(source_dataset=source_dataset, licence="CC0"),
        config_fingerprint=fingerprint_config(fingerprint),
    )
    writer = ShardWriter(root / name, info)
    writer.begin()
    yield writer
    writer.commit()
    (root / name / "template.obj").write_text(sphere_obj()[1])


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
    focal = 2.2 * size
    K = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1.0]])
    fingerprint = {"name": name, "seed": seed}
    with sphere_dataset(root, name, "flat", "full-on", "stage1 test sphere world", fingerprint) as writer:
        for s in range(subjects):
            subject = f"s{s:02d}"
            scale = 1.0 + 0.1 * s
            albedo = cast @ rng.uniform(0.3, 0.8, 3)
            with writer.part(subject) as part:
                part.add_mesh(sphere_mesh(subject, scale))
                for c in range(cameras):
                    angle = 2 * np.pi * c / cameras
                    w2c = look_at_w2c(
                        0.5 * np.array([np.sin(angle), 0.2, np.cos(angle)]), np.zeros(3), [0.0, 1.0, 0.0]
                    )
                    image, mask = render_sphere(scale, albedo, K, w2c, size)
                    camera = f"cam{c:02d}"
                    source = f"{subject}/{camera}.exr"
                    part.add(
                        sphere_image_row(name, subject, camera, "full", "train", K, w2c, image, mask, source)
                    )
    return root / name


def tiny_stage1_preset(**changes):
    """A stage-1 preset sized for tests: UV 16², 32² crops, small decoders, a learning rate that shows
    progress within a few iterations."""
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


def train_script(
    data: list[Path],
    out: Path,
    evaluate: bool = False,
    kill_after_checkpoint: int | None = None,
    **preset_changes,
) -> str:
    """Python source that trains a tiny stage-1 run; for subprocesses (SIGKILL, torchrun).

    With ``kill_after_checkpoint`` N the script prints ``CHECKPOINT N`` once the checkpoint of iteration N is
    saved and waits there to be killed (:func:`helpers.kill_handshake.kill_at`).
    """
    lines = [
        IMPORT_HELPERS,
        "from pathlib import Path",
        "from helpers.stage1_world import tiny_stage1_preset",
        "from relightanyone.model.train import stage1",
    ]
    if kill_after_checkpoint is not None:
        lines += [
            "from helpers.kill_handshake import block_until_killed",
            "save_checkpoint = stage1.save_checkpoint",
            "def save_then_wait(path, payload):",
            "    save_checkpoint(path, payload)",
            f"    if payload['iteration'] == {kill_after_checkpoint}:",
            f"        block_until_killed('CHECKPOINT {kill_after_checkpoint}')",
            "stage1.save_checkpoint = save_then_wait",
        ]
    lines += [
        f"preset = tiny_stage1_preset(**{preset_changes!r})",
        f"data = [Path(p) for p in {[str(d) for d in data]!r}]",
        f"config = stage1.Stage1Config(data, Path({str(out)!r}), preset, progress=False, evaluate={evaluate!r})",
        "stage1.train_stage1(config)",
    ]
    return "\n".join(lines) + "\n"


def sphere_template_binding(folder: Path, uv_size: int):
    """Template vertices (V, 3) float32 and the texel binding of the UV sphere (one seam) at ``uv_size``,
    written to ``folder/template.obj`` and read back."""
    import torch

    from relightanyone.model.networks.gaussians import TexelBinding
    from relightanyone.render.mesh import load_obj
    from relightanyone.render.uv_binding import UVBinding

    path = Path(folder) / "template.obj"
    path.write_text(sphere_obj()[1])
    mesh = load_obj(path)
    uv = UVBinding.from_mesh(mesh.vertices, mesh.faces, mesh.uvs, mesh.face_uvs, uv_size)
    binding = TexelBinding.from_maps(uv.face_index, uv.barycentrics, uv.valid, uv.faces)
    return torch.as_tensor(mesh.vertices, dtype=torch.float32), binding
