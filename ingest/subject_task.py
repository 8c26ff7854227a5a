"""One ingest task: a subject's views decoded, calibrated, put in canonical space, cropped, masked and
encoded into its own part of the :class:`~relightanyone.format.shards.ShardWriter`.

The task function :func:`run_subject_task` is what every executor runs (:mod:`relightanyone.parallel`,
from :func:`.runner.run_tasks`); it holds one subject at a time and returns a few counters. Steps, in
order: decode (:mod:`.decode`) -> colour calibration -> canonical camera -> undistort + crop around the
tracked mesh + resize -> mesh-silhouette mask (times the alpha map) -> encode -> rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relightanyone.align.geometry import transform_points, w2c_to_canonical
from relightanyone.format.codecs import encode_image, encode_mask
from relightanyone.format.schema import ImageRow, MeshRow, QuarantineEntry, build_image_row
from relightanyone.ingest.checks import Finding, view_item
from relightanyone.ingest.decode import (
    DecodeError,
    TaskDecoder,
    apply_colour_calibration,
    set_decoder_threads,
)
from relightanyone.ingest.image_decisions import ImageCheck
from relightanyone.ingest.records import SourceView, SubjectPlan
from relightanyone.ingest.steps import (
    MeshSilhouette,
    crop_box_around_points,
    project_points,
    undistort_crop_resize,
    undistort_crop_resize_valid,
)
from relightanyone.ingest.tracking import (
    AlignmentError,
    FrameAlignment,
    Template,
    TemplateFit,
    load_template,
)
from relightanyone.render.mesh import read_obj_vertices

# Bytes of encoded rows a task keeps for the views the image check holds back (per task, so per worker):
# about 170 rows of 512² or 40 of 1024²; views past it are decoded again when released.
HELD_ROWS_BYTES = 256 * 2**20


@dataclass(frozen=True)
class IngestSettings:
    """Everything a task needs besides its subject; small and picklable."""

    dataset: str
    source_root: str
    template_path: str
    neck_mask_path: str | None
    out_size: int
    margin: float
    encoding: str
    video_threads: int = 1  # FFmpeg threads per task; not part of the dataset's fingerprint
    accepted_checks: tuple[str, ...] = ()  # convention checks overridden on purpose (--accept-check)


@dataclass
class SubjectTask:
    """One subject's views and the alignment of each of its frames (``failures``: frame -> reason)."""

    task: str
    plan: SubjectPlan
    alignments: dict[int, FrameAlignment]
    failures: dict[int, str]
    frame_pairing: str = ""  # how the tracking's timesteps pair with native frames (empty: shipped meshes)
    refused_views: dict[str, str] = field(default_factory=dict)  # item -> why a convention check refused it
    template_fit: TemplateFit | None = None  # the template against the export's canonical shape


@dataclass
class TaskResult:
    task: str
    subject: str
    views: int
    rows: int
    quarantined: int
    bytes: int
    skipped: bool = False
    reasons: dict[str, int] = field(default_factory=dict)


def canonical_mesh(alignment: FrameAlignment, template: Template) -> np.ndarray:
    """``(V, 3)`` the frame's tracked mesh in canonical space (metres)."""

    tracked = alignment.tracked_vertices
    if tracked is None:
        tracked = read_obj_vertices(Path(alignment.mesh_path), template.vertex_count) * alignment.mesh_scale
    return transform_points(alignment.canonical_from_tracker, tracked)


@dataclass(frozen=True)
class FrameMesh:
    """A frame's canonical tracked mesh as its views use it: ``crop_points (P, 3)``, the head vertices the
    crop frames (the neck excluded), and the silhouette the mask is cut from."""

    crop_points: np.ndarray
    silhouette: MeshSilhouette

    @classmethod
    def from_vertices(cls, vertices: np.ndarray, template: Template) -> FrameMesh:
        head = ~template.neck_vertices
        crop_points = vertices[head] if head.sum() >= 3 else vertices
        return cls(crop_points, MeshSilhouette(vertices, template.faces, template.neck_faces))


def normalize_view(
    view: SourceView,
    image: np.ndarray,
    alpha: np.ndarray | None,
    alignment: FrameAlignment,
    mesh: FrameMesh,
    out_size: int,
    margin: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """Steps 3-6 for one calibrated image.

    Args:
        image: ``(H, W, 3)`` float32 colour-calibrated linear RGB; alpha: ``(H, W)`` in [0, 1] or None.
        mesh: the canonical tracked mesh of the view's frame.
    Returns:
        ``(image (S, S, 3) float32, mask (S, S) float32, valid (S, S) bool, K (3, 3), w2c (4, 4), crop
        box)``; the mask is zero wherever ``valid`` is not (the zero padding of a crop past the image).
    """

    camera = view.camera
    height, width = image.shape[:2]
    if (width, height) != (int(camera.width), int(camera.height)):
        raise ValueError(
            f"image is {width}x{height} but the calibration of camera {camera.name} is for "
            f"{camera.width}x{camera.height}"
        )
    w2c = w2c_to_canonical(camera.w2c, alignment.canonical_from_native)
    # The crop is taken from the undistorted image, whose pinhole camera is K itself.
    box = crop_box_around_points(project_points(mesh.crop_points, camera.K, w2c), (width, height), margin)
    out, K_new, valid = undistort_crop_resize_valid(image, camera.K, camera.dist, box, out_size)
    mask = (mesh.silhouette.mask(K_new, w2c, out_size) & valid).astype(np.float32)
    if alpha is not None:
        if alpha.shape != (height, width):
            raise ValueError(f"alpha map is {alpha.shape[1]}x{alpha.shape[0]}, image is {width}x{height}")
        alpha_out, _ = undistort_crop_resize(alpha.astype(np.float32), camera.K, camera.dist, box, out_size)
        mask *= np.clip(alpha_out.reshape(out_size, out_size), 0.0, 1.0)
    return out, mask, valid, K_new, w2c, box


def configure_task_threads(video_threads: int = 1) -> None:
    """One thread per task: parallelism comes from the executor, and results stay deterministic. Only
    the video decoder gets ``video_threads``, the worker's share of the CPUs
    (:func:`relightanyone.parallel.cpu_share`)."""
    import cv2

    cv2.setNumThreads(1)
    set_decoder_threads(avif=1, video=video_threads)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass


def run_subject_task(writer, settings: IngestSettings, task: SubjectTask) -> TaskResult:
    """Decode, calibrate, align, crop, mask and encode one subject's views into its part."""

    configure_task_threads(settings.video_threads)
    plan = task.plan
    result = TaskResult(task.task, plan.subject, len(plan.views), 0, 0, 0)
    template = load_template(
        Path(settings.template_path), settings.neck_mask_path and Path(settings.neck_mask_path)
    )

    def refuse(part, item: str, source: str, reason: str, stage: str) -> None:
        part.quarantine(QuarantineEntry(item=item, source=source, reason=reason, stage=stage))
        result.quarantined += 1
        result.reasons[stage] = result.reasons.get(stage, 0) + 1

    with writer.part(task.task) as part, TaskDecoder(settings.source_root) as decoder:
        for refusal in plan.refusals:
            refuse(part, refusal.item, refusal.source, refusal.reason, "plan")
        meshes: dict[int, FrameMesh] = {}
        for frame, alignment in sorted(task.alignments.items()):
            try:
                vertices = canonical_mesh(alignment, template)
            except ValueError as error:
                task.failures[frame] = f"subject {plan.subject} frame {frame}: {error}"
                continue
            meshes[frame] = FrameMesh.from_vertices(vertices, template)
            part.add_mesh(MeshRow(plan.subject, frame, vertices.astype(np.float32)))
        views = sorted(plan.views, key=lambda v: (v.frame, v.camera.name, v.pattern))
        decoder.prefetch_videos(v.image for v in views if v.frame in meshes)
        seen: set[str] = set()
        image_check = ImageCheck(task, {f: m.silhouette for f, m in meshes.items()}, settings.accepted_checks)

        def normalized_row(view: SourceView, image: np.ndarray, alpha, sha256: str) -> ImageRow:
            image = apply_colour_calibration(image, view.colour)
            out, mask, valid, K, w2c, box = normalize_view(
                view,
                image,
                alpha,
                task.alignments[view.frame],
                meshes[view.frame],
                settings.out_size,
                settings.margin,
            )
            return build_image_row(
                dataset=settings.dataset,
                subject=plan.subject,
                frame=view.frame,
                camera=view.camera.name,
                pattern=view.pattern,
                split=plan.split,
                K=K,
                w2c=w2c,
                image=encode_image(out, settings.encoding),
                image_encoding=settings.encoding,
                mask=encode_mask(mask),
                width=settings.out_size,
                height=settings.out_size,
                source=view.source,
                source_sha256=sha256,
                crop=box,
                colour_matrix=view.colour.applied_matrix(),
                valid=valid,
            )

        # Rows of views the image check holds back, kept (up to HELD_ROWS_BYTES) so that a view it
        # releases is written without decoding its image again; the others are decoded again.
        held_rows: dict[tuple[str, str], ImageRow] = {}  # (item, source) -> row
        held_bytes = 0
        written: dict[str, tuple[str, str, int]] = {}  # item -> (row key, source, bytes)
        for view in image_check.passes(views, decoder.prefetch_videos):
            item = f"{plan.subject}/{view.frame:06d}/{view.camera.name}/{view.pattern}"
            if view.frame not in meshes:
                refuse(part, item, view.source, task.failures.get(view.frame, "no tracked mesh"), "align")
                continue
            if item in task.refused_views:
                refuse(part, item, view.source, task.refused_views[item], "check")
                continue
            if item in seen:
                refuse(part, item, view.source, f"a second image for {item} (first one kept)", "plan")
                continue
            row = held_rows.pop((item, view.source), None)
            if row is None:
                try:
                    image, sha256 = decoder.decode(view.image)
                    alpha = decoder.decode_alpha(view.alpha) if view.alpha is not None else None
                except DecodeError as error:
                    refuse(part, item, view.source, str(error), "decode")
                    continue
                held = image_check.holds(view, item, image)
                try:
                    row = normalized_row(view, image, alpha, sha256)
                except (ValueError, AlignmentError) as error:
                    if not held:
                        refuse(part, item, view.source, f"{view.image.label}: {error}", "normalize")
                    continue  # a held view that is released is decoded again and refused here then
                if held:
                    size = len(row.image) + len(row.mask) + len(row.valid)
                    if held_bytes + size <= HELD_ROWS_BYTES:
                        held_rows[(item, view.source)] = row
                        held_bytes += size
                    continue
            part.add(row)
            seen.add(item)
            result.rows += 1
            result.bytes += len(row.image) + len(row.mask)
            written[item] = (row.key, view.source, len(row.image) + len(row.mask))
        for held_item, held_source, reason in image_check.refusals():
            refuse(part, held_item, held_source, f"check {image_check.check_of(reason)}: {reason}", "check")
        withdrawn = {item: reason for item, reason in image_check.withdrawn().items() if item in written}
        part.withdraw({written[item][0] for item in withdrawn})
        for item, reason in withdrawn.items():
            _, source, size = written[item]
            refuse(part, item, source, f"check {image_check.check_of(reason)}: {reason}", "check")
            result.rows -= 1
            result.bytes -= size
    return result


def check_images(settings: IngestSettings, task: SubjectTask, frames: int | None = None) -> list[Finding]:
    """The image check of a task's views, writing nothing: every frame (``doctor``) or the first ``frames``
    aligned frames (a dry run). One finding per view that fails, its item to quarantine."""
    template = load_template(
        Path(settings.template_path), settings.neck_mask_path and Path(settings.neck_mask_path)
    )
    aligned = sorted(task.alignments.items())[:frames]
    silhouettes = {
        f: FrameMesh.from_vertices(canonical_mesh(a, template), template).silhouette for f, a in aligned
    }
    check = ImageCheck(task, silhouettes, settings.accepted_checks)
    views = sorted(task.plan.views, key=lambda v: (v.frame, v.camera.name, v.pattern))
    with TaskDecoder(settings.source_root) as decoder:
        for view in views:
            if view.frame not in silhouettes or view.pattern != "full":
                continue
            try:
                image, _ = decoder.decode(view.image)
            except DecodeError:
                continue  # the ingest quarantines it with the decoder's reason
            check.holds(view, view_item(view), image)
    refused, _ = check.decide()
    items_by_reason: dict[str, list[str]] = {}
    listed: set[str] = set()
    for item, reason in [*((i, r) for i, _, r in refused), *check.withdrawn().items()]:
        if item not in listed:
            listed.add(item)
            items_by_reason.setdefault(reason, []).append(item)
    # One finding per reason: a swapped pair, or a subject refused as a whole, is one line.
    return [
        Finding(check.check_of(reason), "view", reason, tuple(items))
        for reason, items in items_by_reason.items()
    ]
