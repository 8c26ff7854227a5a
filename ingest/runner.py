"""The shared ingest steps: a :class:`DatasetPlan` in, a normalized dataset out.

Per subject (one task, one ``_parts/<subject>`` of the :class:`ShardWriter`, run by
:func:`.subject_task.run_subject_task`), in this order:

1. decode (:mod:`.decode`; videos once per task) -> 2. colour calibration (linear or display space)
-> 3. cameras into canonical head space, metres (:mod:`.tracking`: native -> tracker -> canonical)
-> 4. undistort -> 5. crop: the square around the projected tracked mesh (above the neck line), resized
to the preset's size, ``K`` updated -> 6. mask: the mesh silhouette cut below the neck line, times the
alpha map where the dataset has one -> 7. encode (the format's default encoding) -> rows.

The coordinator (:func:`ingest_dataset`) relates every frame to the tracking export first (cheap: one
mesh per frame, and it reports camera disagreement before anything is written), writes the lights, the
template and the refusals, runs the tasks on an executor (:mod:`relightanyone.parallel`), skipping tasks
a killed run already finished, and commits. The same plan gives byte-identical datasets on any executor:
every task writes its own part and returns a small :class:`.subject_task.TaskResult`, so the coordinator
never holds pixels, and the commit sorts rows by key.
"""

from __future__ import annotations

import json
import re
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from relightanyone.align.geometry import (
    decompose_similarity,
    fold_head_pose,
    light_intensities_to_canonical,
    lights_to_canonical,
    similarity,
)
from relightanyone.errors import InputError
from relightanyone.format.arrow_io import atomic_write_bytes
from relightanyone.format.codecs import DEFAULT_IMAGE_ENCODING
from relightanyone.format.schema import (
    INGEST_REPORT_NAME,
    NECK_MASK_NAME,
    QUARANTINE_NAME,
    TEMPLATE_NAME,
    DatasetInfo,
    LightRow,
    Provenance,
    QuarantineEntry,
    check_name,
    fingerprint_config,
)
from relightanyone.format.shards import QuarantineLog, ShardWriter
from relightanyone.ingest.checks import CheckReport, check_tasks, view_item
from relightanyone.ingest.records import DatasetPlan, SubjectPlan
from relightanyone.ingest.subject_task import IngestSettings, SubjectTask, check_images, run_subject_task
from relightanyone.ingest.tracking import (
    NECK_MASK_NAMES,
    TRANSFORMS_NAME,
    AlignmentError,
    Template,
    TrackingOptions,
    align_subject,
    check_export_mode,
    find_template,
    load_template,
    shipped_tracking,
)
from relightanyone.parallel import Executor
from relightanyone.progress import progress_bar

# Square crop side per preset (docs/ingest.md: tiny/demo 128², small 512², paper 1024²).
PRESET_SIZES = {"tiny": 128, "demo": 128, "small": 512, "paper": 1024}
CROP_MARGIN = 0.1  # of the head's projected extent, on each side
# Shard bytes per stored pixel, image + mask, as measured by bench/results/loader.json (1024² rows).
BYTES_PER_PIXEL = {"raw-f16": 2.02, "png16": 1.98, "exr-half": 1.38}
TRACKER_NAME = "VHAP export"
SHIPPED_TRACKER_NAME = "meshes shipped with the capture"
SHOWN_REASONS = 5  # refusals and failed frames listed before writing; every one goes to quarantine.jsonl
SHOWN_VALUES = 25  # names listed per line of what was found (cameras, frames, ...)
# A tracked mesh fits the template (or its own canonical shape) to a few mm; far more means other units,
# another topology or another vertex order.
LARGE_FIT_RMS_MM = 20.0
_TASK_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
# What the local pool's server imports once, so each forked worker starts with them loaded.
WORKER_PRELOAD = (
    "relightanyone.ingest.runner",  # the alignment's task function lives here
    "relightanyone.ingest.subject_task",
    "relightanyone.ingest.decode",
    "relightanyone.ingest.steps",
    "relightanyone.ingest.tracking",
    "relightanyone.align.colour",
    "relightanyone.align.geometry",
    "relightanyone.format.codecs",
    "relightanyone.format.shards",
    "cv2",
    "trimesh",
    "torch",  # calibration readers return tensors; importing it in every worker costs seconds
    "relightanyone.ingest.calibration",  # the tracker's cameras (imports kornia: 0.3 s per worker)
)


def ingest_executor(workers: int = 1, executor: str = "local") -> Executor:
    """The executor of an ingest's tasks: ``executor`` "local" (this process, or a kept pool of ``workers``
    processes) or "ray", with the ingest's modules preloaded in the pool's workers."""
    return Executor(executor, workers, preload=WORKER_PRELOAD)


@dataclass
class IngestSummary:
    """What an ingest run did."""

    dataset: str
    path: Path
    rows: int
    quarantined: int
    seconds: float
    bytes: int
    views: int
    subjects: int
    resumed_subjects: int
    camera_disagreement_mm: float
    camera_disagreement_deg: float
    reasons: dict[str, int] = field(default_factory=dict)
    tracker_cameras: int = (
        0  # cameras compared with the tracker's (none for meshes shipped in the native world)
    )
    check_reasons: list[str] = field(default_factory=list)  # what the checks quarantined, most frequent first

    def lines(self) -> list[str]:
        out = [
            f"{self.dataset}: {self.rows} rows written, {self.quarantined} quarantined, "
            f"{self.subjects} subjects ({self.resumed_subjects} resumed), {self.bytes / 1e6:.1f} MB, "
            f"{self.seconds:.1f} s -> {self.path}"
        ]
        if self.tracker_cameras:
            out.append(
                f"native vs tracker cameras: worst {self.camera_disagreement_mm:.3f} mm, "
                f"{self.camera_disagreement_deg:.4f} deg ({self.tracker_cameras} cameras)"
            )
        out += [f"  quarantined ({stage}): {count}" for stage, count in sorted(self.reasons.items())]
        out += [f"    {reason}" for reason in self.check_reasons]
        return out


def task_name(subject: str) -> str:
    """The ShardWriter task of a subject: its name when it is a valid task name, else a stable hash."""
    if _TASK_NAME.match(subject) and not subject.endswith(".tmp"):
        return subject
    import hashlib

    return "subject-" + hashlib.sha1(subject.encode()).hexdigest()[:16]


def subject_tracking_folder(tracking_dir: Path, subject: str) -> Path:
    return Path(tracking_dir) / check_name(subject, "subject", f"tracking folder {tracking_dir}")


def check_plan_names(plan: DatasetPlan) -> None:
    """Raise ``UnsafeNameError`` for a dataset, subject, camera or pattern name of ``plan`` that is not one
    safe file name, naming the native file it came from. Every adapter's plan passes here before any
    path is built from its names (tracking folders, parts, rows, exports)."""
    check_name(plan.dataset, "dataset", f"{plan.source_root} (--name or the {plan.layout} adapter)")
    for subject in plan.subjects:
        check_name(subject.subject, "subject", plan.source_root)
        for view in subject.views:
            where = f"{plan.source_root}/{view.source}"
            check_name(view.camera.name, "camera", where)
            check_name(view.pattern, "pattern", where)


def check_tracking_dir(tracking_dir: Path, subjects: list[str]) -> None:
    """Raise naming what to pass when no subject of the plan has a folder under ``tracking_dir``, or when
    a subject's export is one the toolkit cannot read (VHAP's parameter mode), before anything is read."""
    tracking_dir = Path(tracking_dir)
    if not tracking_dir.is_dir():
        raise FileNotFoundError(f"tracking folder {tracking_dir} does not exist")
    for subject in subjects:
        check_export_mode(subject_tracking_folder(tracking_dir, subject))
    if not subjects or any(
        (subject_tracking_folder(tracking_dir, s) / TRANSFORMS_NAME).is_file() for s in subjects
    ):
        return
    nested = sorted(
        p.name for p in tracking_dir.iterdir() if p.is_dir() and any((p / s).is_dir() for s in subjects)
    )
    hint = f"; the subjects are under {tracking_dir}/{nested[0]}, pass that folder" if nested else ""
    # VHAP names an export after the participant and sequence (074_EMO-1_v16_DS4_...).
    named = sorted(
        p.name
        for p in tracking_dir.iterdir()
        if p.is_dir() and any(p.name.startswith(f"{s}_") for s in subjects)
    )
    if named and not nested:
        hint = (
            f"; {tracking_dir} holds exports named after a sequence ({', '.join(named[:3])}"
            f"{' ...' if len(named) > 3 else ''}): link the one of the ingested sequence as "
            f"{tracking_dir}/<subject> (e.g. ln -s {named[0]} {tracking_dir}/{named[0].split('_')[0]}), "
            "or pass a folder that holds such links"
        )
    raise FileNotFoundError(
        f"{tracking_dir} has no <subject>/{TRANSFORMS_NAME} for any of the subjects "
        f"({', '.join(subjects[:5])}{' ...' if len(subjects) > 5 else ''}){hint}"
    )


def native_cameras_by_frame(plan: SubjectPlan) -> dict[int, dict[str, np.ndarray]]:
    """frame -> camera name -> native ``w2c (4, 4)`` for every frame that has a view.

    The cameras are the whole calibrated rig when the adapter gives it (``plan.rig_w2c``, each frame's head
    pose folded in), so the native->tracker fit does not depend on ``--cameras`` or on dropped images;
    else the views' own cameras.
    """
    frames = sorted({int(view.frame) for view in plan.views})
    if plan.rig_w2c:
        return {
            frame: {
                name: fold_head_pose(w2c, plan.head_poses[frame]) if frame in plan.head_poses else w2c
                for name, w2c in plan.rig_w2c.items()
            }
            for frame in frames
        }
    out: dict[int, dict[str, np.ndarray]] = {}
    for view in plan.views:
        out.setdefault(int(view.frame), {})[view.camera.name] = np.asarray(view.camera.w2c, dtype=np.float64)
    return out


def _align_subject_item(item: tuple, template: Template, options: TrackingOptions):
    """:func:`align_subject` of one ``(subject, native cameras by frame, tracking, clock)`` item."""
    subject, native, tracking, clock = item
    return align_subject(subject, native, tracking, template, clock, options)


def plan_tasks(
    plan: DatasetPlan,
    tracking_dir: Path | None,
    template: Template,
    workers: int = 1,
    executor: str = "local",
    options: TrackingOptions | None = None,
) -> list[SubjectTask]:
    """Relate every (subject, frame) of ``plan`` to the tracking (no pixel is decoded): the VHAP export
    under ``tracking_dir``, or, without one, the meshes the plan ships (custom captures). Subjects are
    aligned in parallel on the ingest's executor."""

    subjects = sorted(plan.subjects, key=lambda s: s.subject)
    items = []
    for subject in subjects:
        if tracking_dir is not None:
            tracking = subject_tracking_folder(tracking_dir, subject.subject)
        else:
            tracking = shipped_tracking(Path(plan.source_root), subject.meshes, plan.mesh_units_to_m)
        clock = (subject.frame_rate, subject.frame_count)
        items.append((subject.subject, native_cameras_by_frame(subject), tracking, clock))
    align = partial(_align_subject_item, template=template, options=options or TrackingOptions())
    aligned = ingest_executor(workers, executor).map(align, items)
    tasks = [
        SubjectTask(
            task_name(subject.subject),
            subject,
            alignments,
            failures,
            pairing if tracking_dir is not None else "",
            template_fit=template_fit,
        )
        for subject, (alignments, failures, pairing, template_fit) in zip(subjects, aligned, strict=True)
    ]
    names = [t.task for t in tasks]
    if len(set(names)) != len(names):
        raise InputError(f"{plan.source_root}: two subjects share a name; subject names must be unique")
    return tasks


def alignment_report(tasks: list[SubjectTask]) -> dict:
    """Per camera, the worst native-vs-tracker disagreement (mm, degrees) over all frames; per subject
    the frames that could not be aligned and the mesh fit residual."""
    per_camera: dict[str, dict[str, float]] = {}
    subjects = {}
    for task in tasks:
        residuals = [a.fit_rms_mm for a in task.alignments.values()]
        subjects[task.plan.subject] = {
            "frame_pairing": task.frame_pairing or None,
            "frames_aligned": len(task.alignments),
            "frames_failed": {str(f): reason for f, reason in sorted(task.failures.items())},
            "mesh_fit_rms_mm": round(max(residuals), 4) if residuals else None,
        }
        for alignment in task.alignments.values():
            for agreement in alignment.agreements:
                entry = per_camera.setdefault(agreement.camera, {"centre_mm": 0.0, "angle_deg": 0.0})
                entry["centre_mm"] = max(entry["centre_mm"], round(agreement.centre_mm, 4))
                entry["angle_deg"] = max(entry["angle_deg"], round(agreement.angle_deg, 5))
    return {"cameras": dict(sorted(per_camera.items())), "subjects": subjects}


def estimate_bytes(views: int, out_size: int, encoding: str) -> int:
    """Expected dataset size from the encoding's measured shard bytes per pixel."""
    return int(views * out_size * out_size * BYTES_PER_PIXEL.get(encoding, 6.0))


# ------------------------------------------------------------------------------------------ coordinator
def _atomic_copy(src: Path, dst: Path) -> None:

    atomic_write_bytes(dst, Path(src).read_bytes())


def mean_similarity(transforms: list[np.ndarray]) -> np.ndarray:
    """The chordal mean of similarities ``(4, 4)``: mean scale, rotation of the mean rotation matrix
    (projected back onto SO(3)), mean translation."""

    parts = [decompose_similarity(T) for T in transforms]
    U, _, Vt = np.linalg.svd(np.mean([R for _, R, _ in parts], axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return similarity(float(np.mean([s for s, _, _ in parts])), R, np.mean([t for _, _, t in parts], axis=0))


def planning_reasons(plan: DatasetPlan) -> list[str]:
    """``item: reason`` of every item refused while planning, in plan order."""
    return [
        f"{r.item}: {r.reason}" for r in [*plan.refusals, *(r for s in plan.subjects for r in s.refusals)]
    ]


def alignment_failures(tasks: list[SubjectTask]) -> list[str]:
    """Why each frame that could not be related to the tracking failed (the reason names subject and frame)."""
    return [reason for task in tasks for _, reason in sorted(task.failures.items())]


def _listed(reasons: list[str], limit: int | None = SHOWN_REASONS) -> list[str]:
    """The first ``limit`` distinct reasons (every one when None) as indented lines, with how often each
    occurs, and how many more there are."""
    counts = Counter(reasons)
    distinct = list(counts)  # first-seen order
    shown = distinct if limit is None else distinct[:limit]
    lines = [f"    {r}" + (f" ({counts[r]} times)" if counts[r] > 1 else "") for r in shown]
    if len(distinct) > len(shown):
        more = len(distinct) - len(shown)
        lines.append(
            f"    ... and {more} more reasons (a written dataset lists every item in quarantine.jsonl)"
        )
    return lines


def listed_values(values, limit: int = SHOWN_VALUES) -> str:
    """``a, b, c`` for a list (``... and N more`` past ``limit``), ``key: value; ...`` for a mapping."""
    if isinstance(values, dict):
        items = [f"{key}: {listed_values(value, limit)}" for key, value in values.items()]
        separator = "; "
    elif isinstance(values, (list, tuple, set)):
        items = [str(value) for value in values]
        separator = ", "
    else:
        return str(values)
    text = separator.join(items[:limit])
    return text + (f" ... and {len(items) - limit} more" if len(items) > limit else "")


def fit_residual_lines(report: dict) -> list[str]:
    """The worst template fit residual of the tracked meshes, flagged when it is too large to be a fit."""
    residuals = {
        subject: entry["mesh_fit_rms_mm"]
        for subject, entry in report["subjects"].items()
        if entry["mesh_fit_rms_mm"] is not None
    }
    if not residuals:
        return []
    subject = max(residuals, key=residuals.get)
    worst = residuals[subject]
    if worst <= LARGE_FIT_RMS_MM:
        return [f"  template fit: worst residual {worst:.3f} mm (subject {subject})"]
    large = sorted(s for s, value in residuals.items() if value > LARGE_FIT_RMS_MM)
    return [
        f"  template fit: residual {worst:.1f} mm for subject {subject} is too large for a fit of the same head "
        f"(over {LARGE_FIT_RMS_MM:g} mm for {len(large)} of {len(residuals)} subjects): the tracked meshes and "
        f"the template differ in units (mm vs m?), topology or vertex order"
    ]


def rig_unplaceable(plan: DatasetPlan, tasks: list[SubjectTask]) -> str | None:
    """Why the light rig of an OLAT plan cannot be placed (no frame aligned), naming the first refusal;
    None when it can be or the plan has no rig."""
    if plan.light_positions is None or any(t.alignments for t in tasks):
        return None
    reasons = planning_reasons(plan) + alignment_failures(tasks)
    first = f"; first: {reasons[0]}" if reasons else ""
    return (
        f"{plan.source_root}: no frame could be aligned, so the light rig cannot be placed and nothing was "
        f"written ({len(reasons)} refusals and failed frames{first})"
    )


def _lights(plan: DatasetPlan, tasks: list[SubjectTask]) -> tuple[list, dict]:
    """Light rows in canonical space and how far the rig lands from there in any one frame (mm).

    The rig is fixed in the native world while heads move a little between frames, so each frame sees it
    from a slightly different canonical pose; ``lights.arrow`` holds one rig, placed with the mean of all
    frames' ``canonical_from_native`` (the mean head pose), and the report gives the largest deviation.
    """

    if plan.light_positions is None:
        return [], {}
    unplaceable = rig_unplaceable(plan, tasks)
    if unplaceable:
        raise AlignmentError(unplaceable)
    transforms = [a.canonical_from_native for t in tasks for _, a in sorted(t.alignments.items())]
    placement = mean_similarity(transforms)
    positions = lights_to_canonical(plan.light_positions, placement)
    intensities = light_intensities_to_canonical(plan.light_intensities, placement)
    full_on = (
        None
        if plan.full_on_light_intensities is None
        else light_intensities_to_canonical(plan.full_on_light_intensities, placement)
    )
    spread = max(
        float(np.linalg.norm(lights_to_canonical(plan.light_positions, T) - positions, axis=1).max() * 1000.0)
        for T in transforms
    )
    rows = [
        LightRow(
            index=k,
            name=f"light-{k:03d}",
            position_m=tuple(positions[k]),
            intensity_rgb=tuple(np.broadcast_to(intensities[k], (3,))),
            pattern=f"olat-{k:03d}",
            full_on_intensity_rgb=None if full_on is None else tuple(np.broadcast_to(full_on[k], (3,))),
        )
        for k in range(len(positions))
    ]
    return rows, {"placement": "mean head pose over all frames", "max_frame_deviation_mm": round(spread, 3)}


def run_checks(
    prepared: tuple[IngestSettings, Template, list[SubjectTask]],
    accepted_checks: tuple[str, ...] = (),
    image_frames: int | None = 0,
) -> CheckReport:
    """The convention checks (:mod:`.checks`) on what :func:`prepare` returned: every check that needs no
    pixel, then the image check on the first ``image_frames`` aligned frames of each subject (None: every
    frame; 0: none, since an ingest's tasks judge each image as they write it)."""
    settings, template, tasks = prepared
    report = check_tasks(tasks, template, accepted_checks)
    if image_frames != 0 and not report.stops:
        settings = replace(settings, accepted_checks=report.accepted)
        for task in tasks:
            report.findings += check_images(settings, task, image_frames)
    return report


def check_lines(report: CheckReport, images_later: bool = False) -> list[str]:
    """The convention checks' findings as printed before writing: one line each, or that all passed.
    ``images_later``: the images are judged as they are written (an ingest), so the line says so."""
    accepted = f" (not applied: {', '.join(report.accepted)})" if report.accepted else ""
    later = "; each image is checked as it is written" if images_later else ""
    if not report.findings:
        return [f"  convention checks: all passed{accepted}{later}"]
    return [f"  convention checks: {len(report.findings)} findings{accepted}"] + [
        f"    {line}" for line in report.lines()
    ]


def refuse_checked_views(tasks: list[SubjectTask], checks: CheckReport) -> None:
    """Give each task the views the convention checks quarantine, with their reasons."""
    refused = checks.refused
    for task in tasks:
        items = {view_item(v) for v in task.plan.views}
        task.refused_views = {item: reason for item, reason in refused.items() if item in items}


def _fingerprint(plan: DatasetPlan, settings: IngestSettings, template: Template) -> str:
    """Changes whenever the plan's views, the settings or the template change (resume safety)."""

    views = [
        (
            v.subject,
            v.frame,
            v.camera.name,
            v.pattern,
            v.image.label,
            v.colour.source,
            np.round(np.asarray(v.camera.w2c), 9).tolist(),
        )
        for s in plan.subjects
        for v in s.views
    ]
    import hashlib

    digest = hashlib.sha256(json.dumps(views, default=str).encode()).hexdigest()
    return fingerprint_config(
        {
            "layout": plan.layout,
            "version": plan.layout_version,
            "views": digest,
            "template": template.sha256,
            "size": settings.out_size,
            "margin": settings.margin,
            "encoding": settings.encoding,
            "split": {s.subject: s.split for s in plan.subjects},
            **({"accepted_checks": settings.accepted_checks} if settings.accepted_checks else {}),
        }
    )


def prepare(
    plan: DatasetPlan,
    tracking_dir: Path | None,
    preset: str,
    template: Path | None = None,
    encoding: str | None = None,
    workers: int = 1,
    executor: str = "local",
    tracking_options: TrackingOptions | None = None,
) -> tuple[IngestSettings, Template, list[SubjectTask]]:
    """Everything before writing: settings, the template and every frame related to the tracking.

    ``tracking_dir`` None uses the meshes the plan ships (custom captures); then ``template`` is needed
    unless the dataset folder holds ``template.obj``. ``workers``/``executor`` as for the ingest itself.
    A template without its neck mask is refused unless ``tracking_options.no_neck_mask``.
    """
    tracking_options = tracking_options or TrackingOptions()

    if preset not in PRESET_SIZES:
        raise ValueError(f"unknown preset {preset!r}; expected one of {', '.join(PRESET_SIZES)}")
    check_plan_names(plan)
    if tracking_dir is None and plan.view_count and not any(s.meshes for s in plan.subjects):
        raise InputError(
            f"{plan.source_root}: the {plan.layout} layout ships no tracked meshes; pass --tracking DIR "
            "(a VHAP export with <subject>/transforms.json)"
        )
    template_path = find_template(Path(tracking_dir or plan.source_root), template)
    loaded = load_template(template_path)
    if loaded.neck_mask_path is None and not tracking_options.no_neck_mask:
        raise InputError(
            f"{template_path}: the template has no neck mask ({' or '.join(NECK_MASK_NAMES)} beside it: one "
            "0/1 per template vertex, 1 = below the neck line), so masks and crops would include the neck; "
            "put it beside the template, or pass --no-neck-mask to ingest without a neck cut"
        )
    if tracking_dir is not None:
        check_tracking_dir(Path(tracking_dir), [s.subject for s in plan.subjects])
    settings = IngestSettings(
        dataset=plan.dataset,
        source_root=str(plan.source_root),
        template_path=str(template_path),
        neck_mask_path=str(loaded.neck_mask_path) if loaded.neck_mask_path else None,
        out_size=PRESET_SIZES[preset],
        margin=CROP_MARGIN,
        encoding=encoding or DEFAULT_IMAGE_ENCODING,
        video_threads=ingest_executor(workers, executor).cpu_share(),
    )
    tracking = Path(tracking_dir) if tracking_dir else None
    tasks = plan_tasks(plan, tracking, loaded, workers, executor, tracking_options)
    return settings, loaded, tasks


def found_lines(
    plan: DatasetPlan, settings: IngestSettings, tasks: list[SubjectTask], every_reason: bool = False
) -> list[str]:
    """What was found, printed before writing: layout, counts, refusals (every distinct reason with
    ``every_reason``, as the dry run prints them), tracking, fit residuals, camera agreement, size."""
    report = alignment_report(tasks)
    limit = None if every_reason else SHOWN_REASONS
    failed = sum(len(t.failures) for t in tasks)
    refused = planning_reasons(plan)
    tracking = (
        f"  tracking: {sum(len(t.alignments) for t in tasks)} frames aligned, {failed} without a usable mesh"
    )
    if report["cameras"]:
        worst_mm = max(c["centre_mm"] for c in report["cameras"].values())
        worst_deg = max(c["angle_deg"] for c in report["cameras"].values())
        tracking += (
            f"; native vs tracker cameras agree to {worst_mm:.3f} mm / {worst_deg:.4f} deg "
            f"({len(report['cameras'])} cameras)"
        )
    lines = [
        f"{plan.source_dataset} ({plan.layout} layout {plan.layout_version}) at {plan.source_root}",
        f"  {len(plan.subjects)} subjects, {plan.view_count} views, {len(refused)} refused while planning",
        *_listed(refused, limit),
        tracking,
        *_listed(alignment_failures(tasks), limit),
        *fit_residual_lines(report),
        *[
            f"  tracking frames: {p}"
            for p in sorted({t.frame_pairing for t in tasks if t.frame_pairing and t.plan.views})
        ],
    ]
    worst = sorted(report["cameras"].items(), key=lambda item: -item[1]["centre_mm"])
    for camera, entry in worst[:5]:
        if entry["centre_mm"] > 1.0 or entry["angle_deg"] > 0.1:
            lines.append(
                f"    camera {camera}: native and tracker differ by {entry['centre_mm']:.2f} mm, "
                f"{entry['angle_deg']:.3f} deg"
            )
    if rig_unplaceable(plan, tasks):
        lines.append(
            "  light rig: cannot be placed, no frame could be aligned; the ingest stops before writing"
        )
    sizes = Counter(f"{v.camera.width}x{v.camera.height}" for s in plan.subjects for v in s.views)
    if sizes:
        lines.append(
            f"  image sizes: {listed_values([f'{k} ({n} views)' for k, n in sorted(sizes.items())])}"
        )
    for key, value in sorted(plan.found.items()):
        lines.append(f"  {key}: {listed_values(value)}")
    writable = sum(1 for t in tasks for v in t.plan.views if int(v.frame) in t.alignments)
    lines.append(
        f"  output: {writable} images of {settings.out_size}x{settings.out_size} ({settings.encoding}), "
        f"about {estimate_bytes(writable, settings.out_size, settings.encoding) / 1e6:.1f} MB"
        + (
            f" (of {plan.view_count} views, the others in frames not aligned)"
            if writable < plan.view_count
            else ""
        )
    )
    return lines


def nothing_to_write(plan: DatasetPlan, tasks: list[SubjectTask]) -> str | None:
    """Why an ingest of ``plan`` would write no row (no view, or no view of an aligned frame), naming the
    first reason; None when some view can be written."""
    if any(int(v.frame) in t.alignments for t in tasks for v in t.plan.views):
        return None
    unplaceable = rig_unplaceable(plan, tasks)  # an OLAT capture says why in the light rig's terms
    if unplaceable:
        return unplaceable
    reasons = planning_reasons(plan) + alignment_failures(tasks)
    first = f"; first: {reasons[0]}" if reasons else ""
    if plan.view_count:
        what = "no view belongs to a frame aligned with the tracking"
    elif reasons:
        what = "no view was planned"
    else:
        what = "no view was found (check --subjects, --cameras and --frames against the capture)"
    return f"{plan.source_root}: nothing to write, {what} ({len(reasons)} refusals and failed frames{first})"


def run_tasks(
    writer: ShardWriter,
    settings: IngestSettings,
    tasks: list[SubjectTask],
    executor: Executor,
    progress: bool,
) -> list:
    """``run_subject_task(writer, settings, task)`` for every task on ``executor``; the results in task
    order. Each subject's part is published here as its task returns (a worker never publishes). The
    progress bar counts views of finished subjects; the longest subjects start first."""
    bar = progress_bar(
        total=sum(len(t.plan.views) for t in tasks),
        desc=f"ingest {settings.dataset}",
        unit="view",
        disable=not progress,
    )

    def done(task: SubjectTask) -> None:
        writer.publish(task.task)
        bar.update(len(task.plan.views))

    try:
        return executor.map(
            partial(run_subject_task, writer, settings),
            tasks,
            on_done=done,
            cost=lambda task: len(task.plan.views),
        )
    finally:
        bar.close()


def ingest_dataset(
    plan: DatasetPlan,
    tracking_dir: Path | None,
    out_root: Path,
    preset: str = "tiny",
    workers: int = 1,
    executor: str = "local",
    progress: bool = True,
    template: Path | None = None,
    encoding: str | None = None,
    prepared: tuple[IngestSettings, Template, list[SubjectTask]] | None = None,
    tracking_options: TrackingOptions | None = None,
    accepted_checks: tuple[str, ...] = (),
    checks: CheckReport | None = None,
) -> IngestSummary:
    """Turn ``plan`` into ``out_root/<plan.dataset>/``; resumes an interrupted run of the same config.

    Args:
        tracking_dir: folder holding ``<subject>/transforms.json`` (a VHAP export per subject); None uses
            the tracked meshes the plan ships (custom captures).
        preset: crop size (``tiny``/``demo`` 128, ``small`` 512, ``paper`` 1024).
        workers, executor: ``"local"`` (process pool) or ``"ray"``; one task per subject.
        template: the template OBJ (default: found next to the tracking export).
        prepared: the result of :func:`prepare` when the caller already ran it (the CLI prints it first).
        tracking_options: what the user states about the tracking (:class:`TrackingOptions`).
        accepted_checks: convention checks not to apply (:mod:`.checks`); recorded in the manifest.
        checks: the convention checks' report when the caller already ran them on ``prepared``.
    Raises:
        ConventionError: a convention check found a dataset-level mistake; nothing is written.
    """

    start = time.perf_counter()
    settings, loaded, tasks = prepared or prepare(
        plan,
        Path(tracking_dir) if tracking_dir else None,
        preset,
        template,
        encoding,
        workers,
        executor,
        tracking_options,
    )
    empty = nothing_to_write(plan, tasks)
    if empty:
        raise InputError(empty)
    checks = checks or check_tasks(tasks, loaded, accepted_checks)
    checks.raise_for_stops(plan.source_root)
    refuse_checked_views(tasks, checks)
    settings = replace(settings, accepted_checks=checks.accepted)
    lights, light_facts = _lights(plan, tasks)
    lighting = (
        f"OLAT light stage: {len(lights)} point lights (lights.arrow) and full-on frames"
        if plan.kind == "olat"
        else "flat, static lighting of the capture"
    )
    info = DatasetInfo(
        name=plan.dataset,
        kind=plan.kind,
        template_mesh_id=loaded.sha256,
        lighting=lighting,
        provenance=Provenance(
            source_dataset=plan.source_dataset,
            licence=plan.licence,
            tracker=TRACKER_NAME if tracking_dir is not None else SHIPPED_TRACKER_NAME,
            template=f"{TEMPLATE_NAME} sha256:{loaded.sha256}"
            + ("" if loaded.neck_mask_path else " (no neck mask: --no-neck-mask, masks include the neck)"),
        ),
        config_fingerprint=_fingerprint(plan, settings, loaded),
        accepted_checks=checks.accepted,
    )
    dataset_dir = Path(out_root) / plan.dataset
    writer = ShardWriter(dataset_dir, info)
    writer.begin()
    if lights:
        writer.write_lights(lights)
    for refusal in plan.refusals:
        writer.quarantine(QuarantineEntry(refusal.item, refusal.source, refusal.reason, stage="plan"))
    _atomic_copy(loaded.path, dataset_dir / TEMPLATE_NAME)
    if loaded.neck_mask_path is not None:
        _atomic_copy(loaded.neck_mask_path, dataset_dir / NECK_MASK_NAME)
    report = {
        "alignment": alignment_report(tasks),
        "lights": light_facts,
        "layout": plan.layout,
        "layout_version": plan.layout_version,
        "source_root": str(plan.source_root),
    }
    atomic_write_bytes(
        dataset_dir / INGEST_REPORT_NAME, (json.dumps(report, indent=1, sort_keys=True) + "\n").encode()
    )

    pending = [t for t in tasks if not writer.has_part(t.task)]
    results = run_tasks(writer, settings, pending, ingest_executor(workers, executor), progress)
    manifest = writer.commit(progress=progress)

    reasons: dict[str, int] = {}
    for result in results:
        for stage, count in result.reasons.items():
            reasons[stage] = reasons.get(stage, 0) + count
    if plan.refusals:
        reasons["plan"] = reasons.get("plan", 0) + len(plan.refusals)
    cameras = report["alignment"]["cameras"].values()
    check_reasons = frequent_check_reasons(dataset_dir / QUARANTINE_NAME)
    if manifest.counts["images"] == 0:
        first = f"; most frequent: {check_reasons[0]}" if check_reasons else ""
        raise InputError(
            f"{dataset_dir}: no row was written, every view was quarantined ({manifest.quarantined} items; "
            f"the reasons are in {dataset_dir / QUARANTINE_NAME}){first}"
        )
    total_bytes = sum(entry.bytes for entry in manifest.shards)
    return IngestSummary(
        dataset=plan.dataset,
        path=dataset_dir,
        rows=manifest.counts["images"],
        quarantined=manifest.quarantined,
        seconds=time.perf_counter() - start,
        bytes=total_bytes,
        views=plan.view_count,
        subjects=len(tasks),
        resumed_subjects=len(tasks) - len(pending),
        camera_disagreement_mm=max((c["centre_mm"] for c in cameras), default=0.0),
        camera_disagreement_deg=max((c["angle_deg"] for c in cameras), default=0.0),
        reasons=reasons,
        tracker_cameras=len(cameras),
        check_reasons=check_reasons,
    )


def frequent_check_reasons(quarantine_path: Path, limit: int = 5) -> list[str]:
    """The distinct reasons of the views the checks quarantined while writing (the image check runs in
    the tasks, after the checks printed before writing), most frequent first, each with its count."""
    reasons = Counter(e.reason for e in QuarantineLog(quarantine_path).entries() if e.stage == "check")
    return [f"{reason} ({count} views)" for reason, count in reasons.most_common(limit)]
