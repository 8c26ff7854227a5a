"""The template mesh and the per-frame similarity from a dataset's native world to canonical head space.

Canonical head space is the tracked mesh's frame (``docs/conventions.md``): the template's frame, metres,
the head never moving. For every (subject, frame) two similarities are estimated and chained::

    canonical_from_native = canonical_from_tracker · tracker_from_native

``tracker_from_native`` (with scale: native calibrations and trackers may use different units) is the
Umeyama fit of the native camera centres onto the tracker's centres of the cameras both know; every
shared camera is then mapped into the tracker world and its disagreement with the tracker's own camera
(centre distance in mm, rotation angle in degrees) is reported. ``canonical_from_tracker`` is rigid
(unit scale): the tracker's meshes are metric, and estimating a scale against a reference of another
shape would shrink or grow the subject's head towards the template's size. The reference is the
subject's own ``canonical.obj`` when the export has one (VHAP's mesh mode writes the tracked shape in the
unposed head frame) and the template otherwise; the fit uses the vertices above the neck line, which
move with the skull.

Each tracked timestep (``timestep_index_original``) is paired with a native frame of the capture by
:func:`timestep_mapping`, from evidence: the rate the user or the export states, checked against the
video's length, or timesteps that only one reading fits; an ambiguous or impossible pairing stops the
ingest (:class:`TrackingMismatchError`) instead of mispairing frames.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relightanyone.align.geometry import (
    camera_centre,
    estimate_canonical_from_mesh,
    transform_points,
    umeyama,
    w2c_to_canonical,
)
from relightanyone.errors import InputError
from relightanyone.hashing import sha256_file
from relightanyone.ingest.calibration import from_transforms_json, load_json
from relightanyone.render.mesh import faces_touching, read_obj, read_obj_vertices

# File names of a VHAP export: the tracking of one subject, and the topology's template and neck mask.
TRANSFORMS_NAME = "transforms.json"
NECK_MASK_NAMES = ("neck_mask.txt", "template_neck_mask.txt")
TEMPLATE_NAMES = ("template.obj", "template/template.obj")
MIN_SHARED_CAMERAS = 3
# VHAP's video preprocessing extracts frames with ffmpeg's fps filter at this rate unless told otherwise.
VHAP_DEFAULT_FPS = 25.0
VHAP_MESH_MODE_FLAG = "--flame-mode mesh"


class AlignmentError(InputError):
    """A frame cannot be brought into canonical space; the message names the subject, frame and cause."""


class TrackingMismatchError(InputError):
    """A tracking export cannot be paired with the capture (its timesteps with the native frames, or its
    export mode); the whole ingest stops, since pairing by guess would mispair every frame."""


@dataclass(frozen=True)
class TrackingOptions:
    """What the user states about the tracking on the command line."""

    tracking_fps: float | None = None  # --tracking-fps: rate the tracked frames were extracted at
    no_neck_mask: bool = False  # --no-neck-mask: accept a template without its neck mask (no neck cut)


@dataclass(frozen=True)
class TimestepMapping:
    """How a tracked timestep (``timestep_index_original``) pairs with a native frame of the capture:
    ``native = round(timestep * scale)``; ``evidence`` says how that was established."""

    scale: float
    evidence: str

    def native(self, timestep: int) -> int:
        return int(math.floor(timestep * self.scale + 0.5))


def _fps(value: float) -> str:
    return f"{value:g} fps"


def timestep_mapping(
    timesteps: list[int],
    export_fps: float | None,
    frame_rate: float | None,
    frame_count: int | None,
    options: TrackingOptions,
    where: str,
) -> TimestepMapping:
    """Establish how the tracked ``timesteps`` pair with native frames, from evidence, or stop.

    ``export_fps``: the frame rate the export states (its ``fps`` key), if any; ``frame_rate`` and
    ``frame_count``: the capture's native video rate and length from its container (None for captures of
    still images, whose tracking names native frames). A stated rate (``--tracking-fps`` first) is
    checked against the video's length; without one, the tracking must be unambiguous: timesteps that
    VHAP's default 25 fps extraction could also have produced stop the ingest with the flag to pass.
    Raises :class:`TrackingMismatchError` naming the cause.
    """
    stated, source = (
        (options.tracking_fps, "--tracking-fps")
        if options.tracking_fps
        else (export_fps, f"the 'fps' of {where}")
        if export_fps
        else (None, "")
    )
    if frame_rate is None or frame_rate <= 0:
        ignored = f"; {source} does not apply" if stated is not None else ""
        return TimestepMapping(
            1.0, f"timesteps are native frame numbers (the capture has no video frame rate{ignored})"
        )
    last = max(timesteps, default=0)
    if stated is not None:
        if stated > frame_rate + 1e-9:
            raise TrackingMismatchError(
                f"{where}: the tracking is said to run at {_fps(stated)} ({source}), faster than the "
                f"{_fps(frame_rate)} video it was made from"
            )
        mapping = TimestepMapping(
            frame_rate / stated,
            f"native frame = round(timestep x {frame_rate:g} / {stated:g}): {_fps(stated)} tracking ({source}) "
            f"of the {_fps(frame_rate)} video",
        )
        if frame_count is not None and mapping.native(last) >= frame_count:
            raise TrackingMismatchError(
                f"{where}: timestep {last} at {_fps(stated)} ({source}) is native frame {mapping.native(last)}, "
                f"past the video's {frame_count} frames: the tracking was not made at that rate from this video"
            )
        return mapping
    if len(set(timesteps)) <= 1:
        return TimestepMapping(1.0, "timesteps are native frame numbers (a single tracked timestep)")
    if frame_count is None:
        return TimestepMapping(1.0, "timesteps are native frame numbers (the video's length is unknown)")
    if last >= frame_count:
        raise TrackingMismatchError(
            f"{where}: tracked timestep {last} is past the video's {frame_count} frames; pass --tracking-fps "
            f"with the rate the tracked frames were extracted at"
        )
    extracted = TimestepMapping(frame_rate / VHAP_DEFAULT_FPS, "").native(last)
    if frame_rate > VHAP_DEFAULT_FPS and extracted < frame_count:
        raise TrackingMismatchError(
            f"{where}: cannot tell how the tracked timesteps pair with the {_fps(frame_rate)} video of "
            f"{frame_count} frames: timesteps 0..{last} are native frames 0..{last} if every frame was tracked, "
            f"or native frames 0..{extracted} if the frames were extracted at VHAP's default "
            f"{_fps(VHAP_DEFAULT_FPS)}; pass --tracking-fps {VHAP_DEFAULT_FPS:g} or --tracking-fps {frame_rate:g}"
        )
    return TimestepMapping(
        1.0,
        f"timesteps are native frame numbers (timestep {last} is past the end of a "
        f"{_fps(VHAP_DEFAULT_FPS)} extraction of the {frame_count}-frame video)",
    )


@dataclass(frozen=True)
class Template:
    """The shared topology: ``vertices (V, 3)``, ``faces (F, 3)``, neck masks per vertex ``(V,)`` and per
    face ``(F,)`` (a face is below the neck line when any of its vertices is), and the file's sha256."""

    path: Path
    vertices: np.ndarray
    faces: np.ndarray
    neck_vertices: np.ndarray
    neck_faces: np.ndarray
    sha256: str
    neck_mask_path: Path | None

    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])


def find_template(tracking_dir: Path, explicit: Path | None = None) -> Path:
    """The template OBJ: ``explicit`` when given, else ``<tracking>/template.obj`` or
    ``<tracking>/template/template.obj``; raises naming the places looked at."""
    if explicit is not None:
        explicit = Path(explicit)
        if not explicit.is_file():
            raise FileNotFoundError(f"template mesh {explicit} does not exist")
        return explicit
    candidates = [Path(tracking_dir) / name for name in TEMPLATE_NAMES]
    candidates += [Path(tracking_dir).parent / name for name in TEMPLATE_NAMES]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    looked = ", ".join(str(c) for c in candidates)
    raise FileNotFoundError(f"no template mesh found (looked at {looked}); pass --template PATH/template.obj")


def _file_signature(path: Path | None) -> tuple | None:
    try:
        stat = Path(path).stat() if path is not None else None
    except OSError:
        return None
    return None if stat is None else (stat.st_mtime_ns, stat.st_size)


def load_template(path: Path, neck_mask_path: Path | None = None) -> Template:
    """Read the template OBJ and its neck mask (one 0/1 per vertex; ``neck_mask.txt`` next to it by
    default; no file means no neck cut). Cached per process while the files are unchanged (pool workers
    live across ingests)."""
    path = Path(path)
    neck_mask_path = Path(neck_mask_path) if neck_mask_path is not None else None
    neck_default = [path.parent / n for n in NECK_MASK_NAMES]
    signature = tuple(_file_signature(p) for p in [path, neck_mask_path, *neck_default])
    return _load_template(path, neck_mask_path, signature)


@functools.lru_cache(maxsize=4)
def _load_template(path: Path, neck_mask_path: Path | None, signature: tuple) -> Template:
    vertices, faces = read_obj(path)
    if faces.size == 0:
        raise InputError(f"{path}: the template has no faces")
    if neck_mask_path is None:
        neck_mask_path = next((path.parent / n for n in NECK_MASK_NAMES if (path.parent / n).is_file()), None)
    neck_vertices = np.zeros(len(vertices), dtype=bool)
    if neck_mask_path is not None:
        values = np.loadtxt(neck_mask_path, dtype=np.float64, ndmin=1)
        if values.shape != (len(vertices),):
            raise InputError(
                f"{neck_mask_path}: neck mask has {values.size} entries for {len(vertices)} template vertices"
            )
        neck_vertices = values > 0.5
    return Template(
        path=path,
        vertices=vertices,
        faces=faces,
        neck_vertices=neck_vertices,
        neck_faces=faces_touching(neck_vertices, faces),
        sha256=sha256_file(path),
        neck_mask_path=Path(neck_mask_path) if neck_mask_path is not None else None,
    )


@dataclass(frozen=True)
class TrackerCamera:
    """A tracker camera in the tracker world, OpenCV axes: ``K (3, 3)``, ``w2c (4, 4)``."""

    name: str
    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int


@dataclass
class VhapSubject:
    """One subject's VHAP export: cameras by id, mesh file per native frame, optional canonical shape."""

    folder: Path
    cameras: dict[str, TrackerCamera]
    meshes: dict[int, Path]
    canonical_mesh: Path | None = None
    mesh_scale: float = 1.0  # mesh coordinates -> metres of the tracker world
    native_world: bool = False  # meshes are in the native world already (no camera fit needed)
    mapping: TimestepMapping = field(default_factory=lambda: TimestepMapping(1.0, "native frame numbers"))

    def mesh_for_frame(self, frame: int) -> Path | None:
        """The tracked mesh of native ``frame``; a single-timestep export (static head) serves every frame."""
        if frame in self.meshes:
            return self.meshes[frame]
        if len(set(self.meshes.values())) == 1:
            return next(iter(self.meshes.values()))
        return None

    def untracked_reason(self, frame: int) -> str:
        """Why native ``frame`` has no mesh, with the frames that are tracked and how they were paired."""
        tracked = sorted(self.meshes)
        shown = ", ".join(map(str, tracked[:8])) + (
            f" ... ({len(tracked)} frames)" if len(tracked) > 8 else ""
        )
        return (
            f"native frame {frame} is not tracked: the tracking export {self.folder} has meshes for native "
            f"frames {shown or 'none'} ({self.mapping.evidence})"
        )


def _integer(entry: dict, field: str, where: str) -> int:
    """``entry[field]`` as an int; ``ValueError`` naming ``where`` and the field for NaN, text, a list..."""
    value = entry[field]
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{where}: field '{field}' is not a frame number ({value!r})") from None


def _native_frame(entry: dict, where: str) -> int:
    """Native frame number of a transforms.json frame: ``timestep_index_original``, else the digits of
    ``timestep_id``, else ``timestep_index``."""
    if "timestep_index_original" in entry:
        return _integer(entry, "timestep_index_original", where)
    ident = str(entry.get("timestep_id", ""))
    digits = "".join(ch for ch in ident.split("_")[-1] if ch.isdigit())
    if digits:
        return int(digits)
    if "timestep_index" in entry:
        return _integer(entry, "timestep_index", where)
    raise InputError(f"{where}: frame has no timestep_index_original, timestep_id or timestep_index")


def check_export_mode(folder: Path) -> None:
    """Raise :class:`TrackingMismatchError` when ``folder`` is a VHAP export in parameter mode (FLAME
    parameters per timestep, no ``meshes/``): the toolkit reads tracked meshes, not FLAME parameters."""
    folder = Path(folder)
    if (folder / "meshes").is_dir() or not (folder / "flame_param").is_dir():
        return
    raise TrackingMismatchError(
        f"{folder}: a VHAP export in parameter mode (flame_param/*.npz, no meshes/), VHAP's default; the "
        f"toolkit reads tracked meshes: export again with VHAP's export_as_nerf_dataset.py {VHAP_MESH_MODE_FLAG}"
    )


def read_vhap_subject(
    folder: Path,
    frame_rate: float | None = None,
    frame_count: int | None = None,
    options: TrackingOptions | None = None,
) -> VhapSubject:
    """Read ``<folder>/transforms.json`` and find ``meshes/{t:05d}.obj`` (VHAP's export, ``docs/ingest.md``).

    Cameras come from :func:`relightanyone.ingest.calibration.from_transforms_json` (OpenGL
    camera-to-world and flipped ``cy`` undone there), one per ``camera_id``. Each frame's timestep
    (``timestep_index_original``) is paired with a native frame by :func:`timestep_mapping`, from the
    capture's ``frame_rate`` and ``frame_count`` (a video's; None for still images).
    """
    folder = Path(folder)
    path = folder / TRANSFORMS_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: expected a VHAP export ({TRANSFORMS_NAME} + meshes/)")
    check_export_mode(folder)
    document, _ = load_json(path)
    rig = from_transforms_json(document, per="camera", name=path)  # checks 'frames' and every camera
    cameras = {}
    for i, name in enumerate(rig.names or ()):
        cameras[str(name)] = TrackerCamera(
            name=str(name),
            K=rig.K[i].numpy().astype(np.float64),
            w2c=rig.w2c[i].numpy().astype(np.float64),
            width=int(rig.width[i]),
            height=int(rig.height[i]),
        )
    meshes_by_timestep: dict[int, Path] = {}
    for i, entry in enumerate(document["frames"]):
        where = f"{path} frames[{i}]"
        timestep = _native_frame(entry, where)
        relative = entry.get("mesh_path")
        if relative is None:
            index = _integer(entry, "timestep_index", where) if "timestep_index" in entry else 0
            relative = f"meshes/{index:05d}.obj"
        if not isinstance(relative, str):
            raise InputError(f"{where}: field 'mesh_path' must be a path, got {relative!r}")
        meshes_by_timestep.setdefault(timestep, folder / relative)
    export_fps = document.get("fps")
    if export_fps is not None and (not isinstance(export_fps, (int, float)) or export_fps <= 0):
        raise InputError(f"{path}: field 'fps' must be a positive frame rate, got {export_fps!r}")
    mapping = timestep_mapping(
        sorted(meshes_by_timestep),
        export_fps,
        frame_rate,
        frame_count,
        options or TrackingOptions(),
        str(path),
    )
    meshes = {mapping.native(t): mesh for t, mesh in meshes_by_timestep.items()}
    canonical = folder / "canonical.obj"
    return VhapSubject(folder, cameras, meshes, canonical if canonical.is_file() else None, mapping=mapping)


@dataclass(frozen=True)
class CameraAgreement:
    """How far a native camera, mapped into the tracker world, is from the tracker's camera."""

    camera: str
    frame: int
    centre_mm: float
    angle_deg: float


@dataclass(frozen=True)
class FrameAlignment:
    """Similarities of one (subject, frame) (all ``(4, 4)``) and the tracked mesh they come from."""

    subject: str
    frame: int
    mesh_path: str
    canonical_from_native: np.ndarray
    canonical_from_tracker: np.ndarray
    tracker_from_native: np.ndarray
    fit_rms_mm: float
    agreements: tuple[CameraAgreement, ...] = field(default_factory=tuple)
    mesh_scale: float = 1.0
    # ``(V, 3)`` the tracked mesh as read for the fit (tracker world, metres), so the ingest task that
    # follows need not read the file again.
    tracked_vertices: np.ndarray | None = field(default=None, repr=False, compare=False)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in degrees of the rotation taking ``R_b`` to ``R_a`` (both ``(3, 3)``)."""
    cosine = (np.trace(R_a @ R_b.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cosine, -1.0, 1.0))))


def fit_tracker_from_native(
    native_w2c: dict[str, np.ndarray], tracker: dict[str, TrackerCamera], frame: int
) -> tuple[np.ndarray, tuple[CameraAgreement, ...]]:
    """Similarity ``tracker_from_native (4, 4)`` from the cameras both rigs know, and the per-camera
    disagreement after the fit. Raises :class:`AlignmentError` with fewer than 3 shared cameras."""

    shared = sorted(name for name in native_w2c if name in tracker)
    if len(shared) < MIN_SHARED_CAMERAS:
        raise AlignmentError(
            f"frame {frame}: only {len(shared)} camera(s) ({', '.join(shared) or 'none'}) are in both the "
            f"native calibration and the tracking export; {MIN_SHARED_CAMERAS} are needed to relate the two worlds"
        )
    native_centres = np.stack([camera_centre(native_w2c[n]) for n in shared])
    tracker_centres = np.stack([camera_centre(tracker[n].w2c) for n in shared])
    try:
        T = umeyama(native_centres, tracker_centres, with_scale=True)
    except ValueError as error:
        raise AlignmentError(f"frame {frame}: cannot relate native and tracker cameras ({error})") from None
    agreements = []
    for name, centre in zip(shared, tracker_centres, strict=True):
        mapped = w2c_to_canonical(native_w2c[name], T)
        agreements.append(
            CameraAgreement(
                camera=name,
                frame=int(frame),
                centre_mm=float(np.linalg.norm(camera_centre(mapped) - centre) * 1000.0),
                angle_deg=rotation_angle_deg(mapped[:3, :3], tracker[name].w2c[:3, :3]),
            )
        )
    return T, tuple(agreements)


def fit_canonical_from_tracker(
    tracked: np.ndarray, reference: np.ndarray, rigid_vertices: np.ndarray
) -> tuple[np.ndarray, float]:
    """Rigid ``canonical_from_tracker (4, 4)`` with ``reference ≈ T @ tracked`` on ``rigid_vertices``
    ``(V,)`` bool, and the RMS residual in mm."""

    mask = rigid_vertices if rigid_vertices.sum() >= 3 else None
    T = estimate_canonical_from_mesh(tracked, reference, vertex_mask=mask, with_scale=False)
    used = slice(None) if mask is None else mask
    residual = transform_points(T, tracked[used]) - reference[used]
    return T, float(np.sqrt(np.mean(np.sum(residual**2, axis=1))) * 1000.0)


def align_frame(
    subject: str,
    frame: int,
    native_w2c: dict[str, np.ndarray],
    vhap: VhapSubject,
    template: Template,
    reference: np.ndarray,
) -> FrameAlignment:
    """Chain the two fits for one (subject, frame); raises :class:`AlignmentError` naming the cause."""
    mesh_path = vhap.mesh_for_frame(frame)
    if mesh_path is None:
        raise AlignmentError(f"subject {subject} frame {frame}: {vhap.untracked_reason(frame)}")
    try:
        tracked = read_obj_vertices(mesh_path, template.vertex_count) * vhap.mesh_scale
    except ValueError as error:
        raise AlignmentError(f"subject {subject} frame {frame}: {error}") from None
    if vhap.native_world:
        tracker_from_native, agreements = np.eye(4), ()
    else:
        tracker_from_native, agreements = fit_tracker_from_native(native_w2c, vhap.cameras, frame)
    canonical_from_tracker, rms_mm = fit_canonical_from_tracker(tracked, reference, ~template.neck_vertices)
    return FrameAlignment(
        subject=subject,
        frame=int(frame),
        mesh_path=str(mesh_path),
        canonical_from_native=canonical_from_tracker @ tracker_from_native,
        canonical_from_tracker=canonical_from_tracker,
        tracker_from_native=tracker_from_native,
        fit_rms_mm=rms_mm,
        agreements=agreements,
        mesh_scale=vhap.mesh_scale,
        tracked_vertices=tracked,
    )


@dataclass(frozen=True)
class TemplateFit:
    """How the user's template compares with the export's own canonical shape (``canonical.obj``), vertex
    by vertex above the neck line: both are the tracking's topology in its canonical frame, in metres, so
    they differ only by the subject's shape. ``extent_ratio`` is the template's size over the shape's;
    ``direct_rms_mm`` the RMS distance as given, ``rigid_rms_mm`` after the best rigid fit, which moves the
    template by ``offset_mm`` and ``offset_deg``."""

    reference: str
    extent_ratio: float
    direct_rms_mm: float
    rigid_rms_mm: float
    offset_mm: float
    offset_deg: float


def fit_template(template: Template, reference: np.ndarray, reference_path: Path) -> TemplateFit:
    """:class:`TemplateFit` of ``template`` against ``reference (V, 3)`` (read from ``reference_path``)."""
    head = ~template.neck_vertices if (~template.neck_vertices).sum() >= 3 else np.ones(len(reference), bool)
    ours, theirs = template.vertices[head], reference[head]
    size = float(np.ptp(theirs, axis=0).max())
    ratio = float(np.ptp(ours, axis=0).max()) / max(size, 1e-12)
    T, rigid_rms_mm = fit_canonical_from_tracker(template.vertices, reference, head)
    direct = np.sqrt(np.mean(np.sum((ours - theirs) ** 2, axis=1))) * 1000.0
    return TemplateFit(
        reference=str(reference_path),
        extent_ratio=ratio,
        direct_rms_mm=float(direct),
        rigid_rms_mm=rigid_rms_mm,
        offset_mm=float(np.linalg.norm(transform_points(T, ours.mean(axis=0)[None])[0] - ours.mean(axis=0)))
        * 1000.0,
        offset_deg=rotation_angle_deg(T[:3, :3], np.eye(3)),
    )


def subject_reference(vhap: VhapSubject, template: Template) -> np.ndarray:
    """``(V, 3)`` the shape the tracked meshes are registered to: the export's ``canonical.obj`` when it
    has one with the template's vertex count, else the template."""
    if vhap.canonical_mesh is not None:
        try:
            return read_obj_vertices(vhap.canonical_mesh, template.vertex_count) * vhap.mesh_scale
        except ValueError:
            pass
    return template.vertices


def shipped_tracking(folder: Path, meshes: dict[int, str], units_to_m: float) -> VhapSubject:
    """Tracking that ships with the dataset (custom captures): meshes already in the native world, so the
    tracker world is the native world (metres after ``units_to_m``) and no camera fit is needed."""
    return VhapSubject(Path(folder), {}, {int(f): Path(p) for f, p in meshes.items()}, None, units_to_m, True)


def align_subject(
    subject: str,
    native_w2c_by_frame: dict[int, dict[str, np.ndarray]],
    tracking: Path | VhapSubject,
    template: Template,
    clock: tuple[float | None, int | None] = (None, None),
    options: TrackingOptions | None = None,
) -> tuple[dict[int, FrameAlignment], dict[int, str], str, TemplateFit | None]:
    """Align every frame of a subject: ``({frame: FrameAlignment}, {frame: reason it failed}, how the
    tracked timesteps pair with native frames, the template against the export's canonical shape or None
    when the template itself is the reference)``.

    ``native_w2c_by_frame``: frame -> camera name -> native ``w2c (4, 4)`` (metres, head pose folded).
    ``tracking``: the subject's VHAP export folder, or an already built :class:`VhapSubject`.
    ``clock``: the capture's native frame rate and frame count (a video's), for :func:`timestep_mapping`.
    A missing tracking folder fails every frame with the path in the reason; a tracking that cannot be
    paired with the capture raises :class:`TrackingMismatchError`.
    """
    failures: dict[int, str] = {}
    alignments: dict[int, FrameAlignment] = {}
    try:
        vhap = tracking if isinstance(tracking, VhapSubject) else read_vhap_subject(tracking, *clock, options)
    except TrackingMismatchError:
        raise
    except (OSError, ValueError, KeyError) as error:
        return {}, {frame: f"subject {subject}: {error}" for frame in native_w2c_by_frame}, "", None
    reference = subject_reference(vhap, template)
    template_fit = None
    if reference is not template.vertices:
        # The fits below use the export's shape, so nothing else would notice a template in other units,
        # another vertex order or another frame.
        template_fit = fit_template(template, reference, vhap.canonical_mesh)
    for frame, native in sorted(native_w2c_by_frame.items()):
        try:
            alignments[frame] = align_frame(subject, frame, native, vhap, template, reference)
        except AlignmentError as error:
            failures[frame] = str(error)
    return alignments, failures, vhap.mapping.evidence, template_fit
