"""One expansion task: the avatar of one subject rendered under every pattern into every source camera,
written as one ShardWriter part.

The task fixes the torch thread count and seeds Python, NumPy and torch before anything random or
order-dependent runs, so a subject's bytes are the same in this process, a pool worker or a Ray worker.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable

import numpy as np

from relightanyone.format.codecs import encode_image
from relightanyone.format.colour_alignment import read_learned_colour
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import MeshRow, build_image_row, make_mesh_key
from relightanyone.hashing import sha256_bytes
from relightanyone.model.fit.fitter import load_relightable_model
from relightanyone.pipelines.expand.avatar import decoded_avatar, fitted_avatar
from relightanyone.pipelines.expand.render import expansion_lightings, render_lightings

_MODELS: dict[tuple[str, str], object] = {}  # loaded once per process (a worker runs many subjects)


def cache_relightable_model(stage1, stage2, device: str = "cpu"):
    """The :class:`~relightanyone.model.fit.fitter.RelightableModel` of two runs on ``device``, loaded once
    per process."""

    key = (str(stage1), str(stage2), str(device))
    if key not in _MODELS:
        _MODELS.clear()
        _MODELS[key] = load_relightable_model(stage1, stage2, device)
    return _MODELS[key]


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's global and torch's generators."""
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def subject_avatar(settings, task, model, source):
    """The task's avatar: decoded (stage-1 subject) or fitted / loaded from the avatars folder; decoded and
    fitted on the model's device."""
    import torch

    frame = task.frames[0]
    if task.known:
        tracked = source.meshes().get(make_mesh_key(task.subject, frame))
        return decoded_avatar(
            model,
            task.stage1_index,
            None if tracked is None else torch.from_numpy(np.asarray(tracked, dtype=np.float32)),
            {"subject": task.subject, "dataset": source.name, "frame": frame},
        )
    return fitted_avatar(
        model,
        settings.source,
        task.subject,
        frame,
        settings.fit_settings(),
        settings.avatars / f"{task.name}.avatar",
        task.fit_fingerprint,
        settings.fit_image_scale,
    )


def run_expand_task(writer, settings, task, on_images: Callable[[int], None] | None = None) -> dict:
    """Render and write one subject; returns a small report (subject, images, avatar kind, seconds).

    Args:
        writer: the dataset's :class:`~relightanyone.format.shards.ShardWriter` (already begun).
        settings: :class:`~relightanyone.pipelines.expand.job.ExpandSettings`.
        task: :class:`~relightanyone.pipelines.expand.job.ExpandTask`.
        on_images: called with the number of images written after each camera (progress in-process).
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(settings.threads)
    try:
        return _render_subject(writer, settings, task, on_images)
    finally:
        torch.set_num_threads(threads)


def _render_subject(writer, settings, task, on_images) -> dict:
    import torch

    start = time.perf_counter()
    seed_everything(settings.seed)
    source = NormalizedDataset(settings.source)
    model = cache_relightable_model(settings.stage1, settings.stage2, settings.device)
    avatar = subject_avatar(settings, task, model, source).to(settings.device)
    light_rows = sorted(NormalizedDataset(model.sources["olat_dataset"]).lights(), key=lambda r: r["index"])
    lightings = expansion_lightings(
        model.rig, [row["pattern"] for row in light_rows], list(settings.envmaps), settings.device
    )
    learned = read_learned_colour(settings.source)
    meshes = source.meshes()
    count = 0
    with writer.part(task.name) as part:
        for frame in task.frames:
            tracked = meshes.get(make_mesh_key(task.subject, frame))
            if tracked is not None:
                part.add_mesh(MeshRow(subject=task.subject, frame=frame, vertices=tracked))
        for key in task.source_keys:
            row = source.row(key)
            images = render_lightings(
                avatar,
                torch.tensor(row.K, dtype=torch.float32, device=settings.device),
                torch.tensor(row.w2c, dtype=torch.float32, device=settings.device),
                row.width,
                row.height,
                lightings,
                settings.lightings_per_pass,
            )
            pixels = images.permute(0, 2, 3, 1).cpu().numpy()
            # The images are in the model's colour space: the camera's learned matrix after the source's
            # own (3×3 @ 3×4: the offset goes through the learned matrix too).
            colour_matrix = (
                row.colour_matrix if learned is None else learned.for_camera(row.camera) @ row.colour_matrix
            )
            source_sha256 = sha256_bytes(row.image)
            valid = row.valid_pixels()  # the source row's padding stays padding in every relit image
            for item, image in zip(lightings, pixels, strict=True):
                part.add(
                    build_image_row(
                        dataset=settings.output.name,
                        subject=task.subject,
                        frame=row.frame,
                        camera=row.camera,
                        pattern=item.pattern,
                        split=row.split,
                        K=row.K,
                        w2c=row.w2c,
                        image=encode_image(image),
                        image_encoding="raw-f16",
                        mask=row.mask,
                        width=row.width,
                        height=row.height,
                        source=row.key,
                        source_sha256=source_sha256,
                        crop=row.crop,
                        colour_matrix=colour_matrix,
                        valid=valid,
                    )
                )
            count += len(lightings)
            if on_images is not None:
                on_images(len(lightings))
    return {
        "subject": task.subject,
        "task": task.name,
        "avatar": "decoded" if task.known else "fitted",
        "images": count,
        "seconds": time.perf_counter() - start,
    }
