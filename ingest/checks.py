"""Convention checks: evidence in a capture's own inputs that its cameras, units and images are what the
adapter was told they are, before any row is written.

Every check is a pure function of what an adapter and the tracking alignment already parsed (cameras
``K``/``w2c`` and image sizes, the tracked mesh of every frame, the template and the fit residual) or of a
decoded image. When a check fails, the alternative explanations are tested on the same evidence (invert
the matrices, flip the camera axes, transpose the rotations, rescale ``K`` or the units, flip the image,
give the image to another camera) and the finding names the one that makes the evidence agree, with the
fix.

Scope: a check that fails on at least :data:`SUBJECT_SHARE` of a subject's views (or frames) is a
dataset-level mistake and stops the ingest before anything is written (:class:`ConventionError`); one that
fails on fewer quarantines those views with the reason (stage ``"check"``). ``accepted`` checks
(``--accept-check NAME``) are not applied; the manifest records them. Names, thresholds and overrides are
listed in ``docs/ingest.md`` ("Checks").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from relightanyone.align.geometry import (
    decompose_similarity,
    invert_similarity,
    transform_points,
)
from relightanyone.errors import InputError
from relightanyone.ingest.records import SourceView

# name -> what it checks (docs/ingest.md lists each with its threshold and the causes it names).
CHECKS: dict[str, str] = {
    "rotation": "camera rotations are orthonormal with determinant +1",
    "principal-point": "principal points lie inside their images",
    "surround": "the cameras surround the head: seen from it, they are spread over an angle",
    "in-front": "the tracked head is in front of every camera",
    "facing": "every camera faces the head: the head's centre projects inside its image",
    "projection": "the head projects inside each image at a plausible size",
    "head-size": "the tracked head has a metric size",
    "rig-distance": "cameras are at a metric distance from the head",
    "fit-residual": "the tracked mesh fits the template",
    "lens": "distortion coefficients are those of a real lens, in OpenCV's order",
    "silhouette": "the projected head lies on the image's own foreground",
    "colour-order": "colour images are in RGB order: on the head, red is above blue",
}
CAMERA_CHECKS = ("rotation", "principal-point", "in-front", "facing", "projection")

HEAD_SIZE_M = (0.12, 0.40)  # largest side of the head's bounding box above the neck line
RIG_DISTANCE_M = (0.3, 6.0)  # camera centre to the head's centre
FIT_RMS_MM = 25.0  # rigid fit of a frame's tracked mesh to the template (or canonical shape), above the neck
TANGENTIAL_MAX = 0.05  # |p1|, |p2| of a real lens are about 1e-3; larger ones are coefficients out of order
ROTATION_TOLERANCE = 1e-3  # largest entry of R Rᵀ - I
PROJECTED_INSIDE = 0.5  # share of the projected head's bounding box that must lie inside the image
PROJECTED_EXTENT = (0.03, 4.0)  # projected head extent / the image's larger side
SURROUND_MIN_DEG = 10.0  # the largest angle between two cameras seen from the head's centre
SUBJECT_SHARE = 0.5  # a failure on this share of a subject's views or frames is a dataset-level mistake
EXPLAINED_SHARE = 0.9  # an alternative explains a failure when this share of the views then passes
HEAD_POINTS = 200  # vertices used for the camera checks (evenly subsampled)


class ConventionError(InputError):
    """A dataset-level convention mistake; the message has one line per finding."""


@dataclass(frozen=True)
class Finding:
    """One failed check: ``scope`` ``"dataset"`` (stops) or ``"view"`` (``items`` are quarantined)."""

    check: str
    scope: str
    message: str
    items: tuple[str, ...] = ()

    def line(self) -> str:
        where = f" ({len(self.items)} views quarantined)" if self.items else ""
        return f"check {self.check}: {self.message}{where} [override: --accept-check {self.check}]"


@dataclass
class CheckReport:
    """The findings of a run of the checks; ``refused`` maps a view item to the reason it is quarantined."""

    findings: list[Finding] = field(default_factory=list)
    accepted: tuple[str, ...] = ()

    @property
    def stops(self) -> list[Finding]:
        return [f for f in self.findings if f.scope == "dataset"]

    @property
    def refused(self) -> dict[str, str]:
        return {
            item: f"check {f.check}: {f.message}"
            for f in self.findings
            if f.scope == "view"
            for item in f.items
        }

    def lines(self) -> list[str]:
        return [f.line() for f in self.findings]

    def raise_for_stops(self, where: str, listed: bool = False) -> None:
        """Raise :class:`ConventionError` when a finding is dataset-level (nothing is written): its message
        lists every such finding, or with ``listed`` (the command printed them) only counts them."""
        if not self.stops:
            return
        if listed:
            raise ConventionError(
                f"{where}: {len(self.stops)} convention check finding(s) above stop the ingest, nothing "
                "written (--accept-check NAME overrides a check on purpose)"
            )
        lines = "\n".join(f.line() for f in self.stops)
        raise ConventionError(f"{where}: the convention checks stop the ingest, nothing written:\n{lines}")


def checked_names(accepted: Iterable[str]) -> tuple[str, ...]:
    """``accepted`` as a sorted tuple; an unknown name is an input error listing the known ones."""
    names = tuple(sorted(set(accepted)))
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        raise InputError(f"unknown check {', '.join(unknown)}; the checks are {', '.join(CHECKS)}")
    return names


# --------------------------------------------------------------------------------------- camera checks
@dataclass(frozen=True)
class CameraCase:
    """One camera of one frame as an adapter gave it: ``K (3, 3)``, ``w2c (4, 4)`` native, image size, and
    ``head (N, 3)``, the frame's tracked head in the same native world."""

    items: tuple[str, ...]  # the views of this camera and frame (one per image pattern)
    camera: str
    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    head: np.ndarray


def camera_problem(K: np.ndarray, w2c: np.ndarray, width: int, height: int, head: np.ndarray) -> str | None:
    """The first camera check (:data:`CAMERA_CHECKS` order) that ``K (3, 3)``, ``w2c (4, 4)`` fail against
    the head points ``(N, 3)`` in their world, as ``"name: detail"``; None when all pass."""
    R = w2c[:3, :3]
    error = float(np.abs(R @ R.T - np.eye(3)).max())
    determinant = float(np.linalg.det(R))
    if error > ROTATION_TOLERANCE or determinant < 0:
        return f"rotation: R Rᵀ differs from I by {error:.2g}, det {determinant:+.3f}"
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        return f"principal-point: ({cx:.0f}, {cy:.0f}) px for a {width}x{height} image"
    cam = head @ R.T + w2c[:3, 3]
    in_front = int(np.count_nonzero(cam[:, 2] > 0))
    if in_front < len(cam):
        return f"in-front: {len(cam) - in_front}/{len(cam)} head points behind the camera"
    fx, fy = float(K[0, 0]), float(K[1, 1])
    pixels = cam[:, :2] / cam[:, 2:3] * [fx, fy] + [cx, cy]
    centre = cam.mean(axis=0)
    u, v = centre[0] / centre[2] * fx + cx, centre[1] / centre[2] * fy + cy
    if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
        return (
            f"facing: the head's centre projects to ({u:.0f}, {v:.0f}) px, outside the {width}x{height} image"
        )
    low, high = pixels.min(axis=0), pixels.max(axis=0)
    extent = float(max(high - low))
    inside = np.clip(np.minimum(high, [width - 0.5, height - 0.5]) - np.maximum(low, -0.5), 0, None)
    share = float(np.prod(inside) / max(np.prod(np.maximum(high - low, 1e-9)), 1e-9))
    relative = extent / max(width, height)
    if share < PROJECTED_INSIDE or not PROJECTED_EXTENT[0] <= relative <= PROJECTED_EXTENT[1]:
        return (
            f"projection: the head spans {extent:.0f} px ({relative:.2f} of the image), "
            f"{share:.0%} of it inside the {width}x{height} image"
        )
    return None


def _flip_yz(w2c: np.ndarray) -> np.ndarray:
    return np.diag([1.0, -1.0, -1.0, 1.0]) @ w2c


def _transposed(w2c: np.ndarray) -> np.ndarray:
    out = w2c.copy()
    out[:3, :3] = w2c[:3, :3].T
    return out


def _centred_pp(K: np.ndarray, width: int, height: int) -> np.ndarray:
    out = K.copy()
    out[0, 2] += (width - 1) / 2
    out[1, 2] += (height - 1) / 2
    return out


def _scaled_K(K: np.ndarray, factor: float) -> np.ndarray:
    """``K`` of an image ``factor`` times smaller (the half-pixel resize rule)."""
    out = K.copy()
    out[:2, :2] /= factor
    out[:2, 2] = (K[:2, 2] + 0.5) / factor - 0.5
    return out


# (what it would mean, the fix, how to apply it to (K, w2c, width, height))
Alternative = tuple[str, str, Callable[[np.ndarray, np.ndarray, int, int], tuple[np.ndarray, np.ndarray]]]
CAMERA_ALTERNATIVES: tuple[Alternative, ...] = (
    (
        "these look like camera-to-world matrices",
        "invert them (w2c is the inverse of a camera's pose)",
        lambda K, w2c, w, h: (K, np.linalg.inv(w2c)),
    ),
    (
        "these look like OpenGL camera axes (y up, z backward)",
        "flip the cameras' y and z axes (w2c = diag(1, -1, -1, 1) · w2c)",
        lambda K, w2c, w, h: (K, _flip_yz(w2c)),
    ),
    (
        "these look like camera-to-world matrices with OpenGL axes (the NeRF/Blender convention)",
        "invert them and flip the cameras' y and z axes",
        lambda K, w2c, w, h: (K, _flip_yz(np.linalg.inv(w2c))),
    ),
    (
        "the rotations look transposed",
        "transpose each camera's 3x3 rotation",
        lambda K, w2c, w, h: (K, _transposed(w2c)),
    ),
    (
        "the principal points look like offsets from the image centre",
        "add ((W - 1) / 2, (H - 1) / 2) to them",
        lambda K, w2c, w, h: (_centred_pp(K, w, h), w2c),
    ),
)
K_FACTORS = (2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 32)


def _passing(cases: list[CameraCase], change) -> int:
    """How many ``cases`` pass every camera check after ``change(K, w2c, width, height)``."""
    count = 0
    for case in cases:
        K, w2c = change(case.K, case.w2c, case.width, case.height)
        if camera_problem(K, w2c, case.width, case.height, case.head) is None:
            count += 1
    return count


def _centre_offset(cases: list[CameraCase], factor: float) -> float:
    """Median distance of the principal points from the image centres, in image sizes, after scaling
    ``K`` down by ``factor``."""
    offsets = [
        max(
            abs(_scaled_K(c.K, factor)[0, 2] / (c.width - 1) - 0.5),
            abs(_scaled_K(c.K, factor)[1, 2] / (c.height - 1) - 0.5),
        )
        for c in cases
    ]
    return float(np.median(offsets))


def _median_pp(cases: list[CameraCase]) -> str:
    cx = float(np.median([c.K[0, 2] for c in cases]))
    cy = float(np.median([c.K[1, 2] for c in cases]))
    width = int(np.median([c.width for c in cases]))
    height = int(np.median([c.height for c in cases]))
    return f"principal points at ({_px(cx)}, {_px(cy)}) px for {width}x{height} images"


def _px(value: float) -> str:
    return f"{value / 1000:.1f}k" if abs(value) >= 1000 else f"{value:.0f}"


def explain_cameras(cases: list[CameraCase]) -> str | None:
    """The alternative that makes at least :data:`EXPLAINED_SHARE` of ``cases`` pass every camera check,
    as ``"cause (k/n ... then pass) — fix"``; None when none does."""
    n = len(cases)
    best: tuple[int, str] | None = None
    for meaning, fix, change in CAMERA_ALTERNATIVES:
        passed = _passing(cases, change)
        if passed >= EXPLAINED_SHARE * n and (best is None or passed > best[0]):
            best = (passed, f"{meaning} (changed so, {passed}/{n} views see the head as they should) — {fix}")
    # Several factors may put the head inside the images; the one that brings the principal points
    # nearest the image centres is the size K was calibrated at. A factor that moves them away from the
    # centres only shrinks the view until the head fits: it explains nothing.
    as_given = _centre_offset(cases, 1)
    factors = [f for f in K_FACTORS if _centre_offset(cases, f) < as_given]
    for factor in sorted(factors, key=lambda f: _centre_offset(cases, f)):
        passed = _passing(cases, lambda K, w2c, w, h, f=factor: (_scaled_K(K, f), w2c))
        if passed >= EXPLAINED_SHARE * n and (best is None or passed > best[0]):
            best = (
                passed,
                f"K fits an image {factor}x larger: {_median_pp(cases)} (rescaled, {passed}/{n} views pass) "
                "— give K in pixels of the image files",
            )
    return None if best is None else best[1]


def camera_spread_deg(cases: list[CameraCase]) -> float:
    """The largest angle (degrees) between the directions from the head's centre to two cameras."""
    directions = []
    for case in cases:
        offset = -case.w2c[:3, :3].T @ case.w2c[:3, 3] - case.head.mean(axis=0)
        length = float(np.linalg.norm(offset))
        if length > 0:
            directions.append(offset / length)
    if len(directions) < 2:
        return 180.0
    cosines = np.stack(directions) @ np.stack(directions).T
    return math.degrees(math.acos(float(np.clip(cosines.min(), -1.0, 1.0))))


def surround_findings(cases: list[CameraCase], subject: str, accepted: tuple[str, ...]) -> list[Finding]:
    """A rig whose cameras (one case each) all sit in one direction from the head, closer than
    :data:`SURROUND_MIN_DEG`: the extrinsics are read in the wrong convention (a camera-to-world matrix
    read as world-to-camera puts every camera of a rig aimed at the world's origin at one point)."""
    cameras = list({c.camera: c for c in cases}.values())
    if "surround" in accepted or len(cameras) < 3:
        return []
    spread = camera_spread_deg(cameras)
    if spread >= SURROUND_MIN_DEG:
        return []
    cause = "check the extrinsics' convention and that the meshes are in the cameras' world"
    for meaning, fix, change in CAMERA_ALTERNATIVES:
        changed = [
            CameraCase(c.items, c.camera, *change(c.K, c.w2c, c.width, c.height), c.width, c.height, c.head)
            for c in cameras
        ]
        passed = _passing(changed, lambda K, w2c, w, h: (K, w2c))
        if camera_spread_deg(changed) >= SURROUND_MIN_DEG and passed >= EXPLAINED_SHARE * len(cameras):
            cause = f"{meaning} (changed so, they surround it and {passed}/{len(cameras)} see it) — {fix}"
            break
    return [
        Finding(
            "surround",
            "dataset",
            f"subject {subject}: seen from the head, the {len(cameras)} cameras lie within {spread:.1f} deg of "
            f"one another: {cause}",
        )
    ]


def camera_findings(cases: list[CameraCase], subject: str, accepted: tuple[str, ...]) -> list[Finding]:
    """Camera checks of one subject's views: one finding per failed check, dataset-level when at least
    :data:`SUBJECT_SHARE` of the views fail it (with the alternative that explains them), else the
    failing views' items to quarantine."""
    failures: dict[str, list[tuple[CameraCase, str]]] = {}
    for case in cases:
        problem = camera_problem(case.K, case.w2c, case.width, case.height, case.head)
        if problem is not None:
            name, detail = problem.split(": ", 1)
            if name not in accepted:
                failures.setdefault(name, []).append((case, detail))
    failing = sum(len(f) for f in failures.values())
    if failing >= SUBJECT_SHARE * len(cases):
        # A convention mistake of the rig: one finding, for the check most views fail (the first in
        # order on a tie), with the explanation tested on every view.
        name = max(CAMERA_CHECKS, key=lambda n: (len(failures.get(n, ())), -CAMERA_CHECKS.index(n)))
        case, detail = failures[name][0]
        cause = explain_cameras(cases) or _UNEXPLAINED[name]
        counts = ", ".join(f"{n} {len(failures[n])}" for n in CAMERA_CHECKS if n in failures)
        return [
            Finding(
                name,
                "dataset",
                f"subject {subject}: {failing}/{len(cases)} views fail ({counts}; camera {case.camera}: "
                f"{detail}): {cause}",
            )
        ]
    findings = []
    for name in CAMERA_CHECKS:
        failed = failures.get(name, [])
        if failed:
            cameras = sorted({c.camera for c, _ in failed})
            cause = explain_cameras([c for c, _ in failed]) or "check their K and extrinsics"
            findings.append(
                Finding(
                    name,
                    "view",
                    f"subject {subject}, cameras {_names(cameras)}: camera {failed[0][0].camera}: "
                    f"{failed[0][1]}; the other cameras pass, so these cameras' calibration is wrong: {cause}",
                    tuple(item for c, _ in failed for item in c.items),
                )
            )
    return findings


_UNEXPLAINED = {
    "rotation": "the rotations are not rigid (a scaled or mirrored matrix?) — give orthonormal rotations",
    "principal-point": "K is not in pixels of these images — give K for the image files' size",
    "in-front": "no simple change of convention (inverse, OpenGL axes, transpose) puts the head in front "
    "— check the extrinsics and that the meshes are in the cameras' world",
    "facing": "the cameras look past the head — check the extrinsics and that the meshes are in the "
    "cameras' world",
    "projection": "the head lands outside the images or at an implausible size — check K, the units and "
    "the extrinsics",
}


def _names(names: list[str], shown: int = 6) -> str:
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more


# ------------------------------------------------------------------------------------------ size checks
UNIT_FACTORS = {"mm": 1e-3, "cm": 1e-2}  # unit a capture may be in -> metres


def size_findings(
    subject: str,
    head_extent_m: float,
    cameras: np.ndarray,
    heads: np.ndarray,
    native_to_m: float,
    accepted: tuple[str, ...],
) -> list[Finding]:
    """The head's size and the cameras' distance from it against :data:`HEAD_SIZE_M` and
    :data:`RIG_DISTANCE_M`; when they fail, the unit mistake that explains them.

    ``head_extent_m``: the tracked head's extent (metres as declared); ``cameras (C, 3)`` the views' camera
    centres and ``heads (C, 3)`` the head's centre of each view's frame, both in the native world, whose
    units are ``native_to_m`` metres.
    """

    def distance(head_factor: float, camera_factor: float) -> float:
        gaps = np.linalg.norm(camera_factor * cameras - head_factor * heads, axis=1) * native_to_m
        return float(np.median(gaps))

    def sizes_fit(head_factor: float, camera_factor: float) -> bool:
        head_ok = HEAD_SIZE_M[0] <= head_extent_m * head_factor <= HEAD_SIZE_M[1]
        rig_ok = RIG_DISTANCE_M[0] <= distance(head_factor, camera_factor) <= RIG_DISTANCE_M[1]
        return (head_ok or "head-size" in accepted) and (rig_ok or "rig-distance" in accepted)

    if len(cameras) == 0 or sizes_fit(1.0, 1.0):
        return []
    facts = f"subject {subject}: the head is {head_extent_m:.3g} m across, the cameras {distance(1, 1):.3g} m from it"
    for unit, factor in UNIT_FACTORS.items():
        if sizes_fit(factor, 1.0):
            return [
                Finding(
                    "head-size",
                    "dataset",
                    f"{facts}: the mesh is {1 / factor:.0f}x larger than the rig "
                    f"— template or meshes in {unit}? Give them in metres, like the cameras",
                )
            ]
        if sizes_fit(factor, factor):
            return [
                Finding(
                    "head-size",
                    "dataset",
                    f"{facts}: the whole capture looks like {unit} declared as "
                    f"metres — declare its units (or convert it to metres)",
                )
            ]
        if sizes_fit(1.0, factor):
            return [
                Finding(
                    "rig-distance",
                    "dataset",
                    f"{facts}: camera translations in {unit}? — give them in metres, like the meshes",
                )
            ]
    head_ok = HEAD_SIZE_M[0] <= head_extent_m <= HEAD_SIZE_M[1] or "head-size" in accepted
    name = "rig-distance" if head_ok else "head-size"
    return [
        Finding(
            name,
            "dataset",
            f"{facts}: no unit (mm, cm, m) explains it — check the units of the cameras and the meshes",
        )
    ]


def fit_findings(
    subject: str,
    residuals_mm: dict[int, float],
    items_by_frame: dict[int, list[str]],
    tracked_extent_m: float,
    reference_extent_m: float,
    accepted: tuple[str, ...],
) -> list[Finding]:
    """Frames whose tracked mesh fits the template (or canonical shape) worse than :data:`FIT_RMS_MM`;
    the extents (m, as read) say whether the two are in different units."""
    if "fit-residual" in accepted or not residuals_mm:
        return []
    bad = sorted(f for f, rms in residuals_mm.items() if rms > FIT_RMS_MM)
    if not bad:
        return []
    worst = max(residuals_mm[f] for f in bad)
    ratio = tracked_extent_m / max(reference_extent_m, 1e-12)
    if ratio > 3 or ratio < 1 / 3:
        cause = (
            f"the template is {_times(ratio)} {'smaller' if ratio > 1 else 'larger'} than the tracked "
            f"meshes (head {reference_extent_m:.3g} against {tracked_extent_m:.3g} m across): "
            f"{_metric_one(tracked_extent_m, reference_extent_m)}"
        )
    else:
        cause = (
            "the tracked meshes do not match the template's vertex order or shape "
            "— use the template of the tracking's topology"
        )
    facts = (
        f"subject {subject}: frames {_names([str(f) for f in bad])} fit the template with {worst:.0f} mm RMS "
    )
    facts += f"(limit {FIT_RMS_MM:.0f} mm)"
    if len(bad) >= SUBJECT_SHARE * len(residuals_mm):
        return [Finding("fit-residual", "dataset", f"{facts}: {cause}")]
    items = tuple(item for f in bad for item in items_by_frame.get(f, []))
    return [Finding("fit-residual", "view", f"{facts}; other frames fit, so these meshes are wrong", items)]


def _times(ratio: float) -> str:
    """``ratio`` (or its inverse) as a factor, ``about 1000x`` when it is within 10 % of a unit change."""
    factor = max(ratio, 1 / ratio)
    for unit in (10.0, 100.0, 1000.0):
        if abs(factor / unit - 1) < 0.1:
            return f"about {unit:.0f}x"
    return f"{factor:.0f}x"


def _metric_one(tracked_m: float, template_m: float) -> str:
    """Which of the tracked meshes and the template has a head's size in metres, and the fix."""
    low, high = HEAD_SIZE_M
    if low <= tracked_m <= high:
        return "the meshes have a head's size in metres, so the template is not in metres — give it in metres"
    if low <= template_m <= high:
        return (
            "the template has a head's size in metres, so the meshes are not — give them in metres (or "
            "declare the units they are in)"
        )
    return "neither has a head's size in metres — give both in metres"


def template_findings(subject: str, template_path, fit, accepted: tuple[str, ...]) -> list[Finding]:
    """The user's template against the export's canonical shape (a
    :class:`~relightanyone.ingest.tracking.TemplateFit`, or None when the template is the reference): a
    template in other units, another vertex order or another frame than the tracking stops the ingest."""
    if fit is None or "fit-residual" in accepted:
        return []
    facts = (
        f"subject {subject}: the template {template_path} against the tracking's own shape {fit.reference}"
    )
    ratio = fit.extent_ratio
    if ratio > 3 or ratio < 1 / 3:
        cause = (
            f"{facts}: the template is {_times(ratio)} {'larger' if ratio > 1 else 'smaller'}: "
            "in mm? give the template in metres, like the tracking"
        )
    elif fit.rigid_rms_mm > FIT_RMS_MM:
        cause = (
            f"{facts}: {fit.rigid_rms_mm:.0f} mm RMS after the best rigid fit (limit {FIT_RMS_MM:.0f} mm): "
            "another vertex order or topology — use the tracking's template (FLAME's for VHAP) in its own "
            "vertex order (load OBJs without merging or reordering vertices)"
        )
    elif fit.direct_rms_mm > FIT_RMS_MM:
        cause = (
            f"{facts}: {fit.direct_rms_mm:.0f} mm RMS as given but {fit.rigid_rms_mm:.0f} mm once moved by "
            f"{fit.offset_mm:.0f} mm / {fit.offset_deg:.0f}°: the template is in another frame — canonical "
            "space is the tracking's, give the template in it"
        )
    else:
        return []
    return [Finding("fit-residual", "dataset", cause)]


def extent(points: np.ndarray) -> float:
    """Largest side of the bounding box of ``points (N, 3)``."""
    return float(np.ptp(points, axis=0).max()) if len(points) else 0.0


def subsample(points: np.ndarray, count: int = HEAD_POINTS) -> np.ndarray:
    """At most ``count`` of ``points (N, 3)``, evenly spaced in index order."""
    if len(points) <= count:
        return points
    return points[np.linspace(0, len(points) - 1, count).round().astype(int)]


def head_in_native(tracked: np.ndarray, tracker_from_native: np.ndarray) -> np.ndarray:
    """``(N, 3)`` tracked points (tracker world, metres) in the native world of the cameras."""
    return transform_points(invert_similarity(tracker_from_native), tracked)


def view_item(view: SourceView) -> str:
    """The quarantine item of a view: ``subject/frame/camera/pattern``."""
    return f"{view.subject}/{view.frame:06d}/{view.camera.name}/{view.pattern}"


def lens_findings(views: list[SourceView], subject: str, accepted: tuple[str, ...]) -> list[Finding]:
    """Tangential coefficients (OpenCV's ``p1``, ``p2``: the 3rd and 4th) beyond a real lens's on at least
    :data:`SUBJECT_SHARE` of the cameras: radial terms written in their place, a rig-wide mistake that
    stops the ingest. A single camera with large ones is left alone: real calibrations have a few (one of
    the 40 cameras of a released FaceOLAT calibration has p1 = 0.32)."""
    if "lens" in accepted:
        return []
    cameras = {v.camera.name: v.camera for v in views}
    bad: dict[str, tuple[float, float]] = {}
    for name, camera in cameras.items():
        dist = np.asarray(camera.dist if camera.dist is not None else (), np.float64).reshape(-1)
        if dist.size >= 4 and max(abs(dist[2]), abs(dist[3])) > TANGENTIAL_MAX:
            bad[name] = (float(dist[2]), float(dist[3]))
    if not bad:
        return []
    name = sorted(bad)[0]
    message = (
        f"subject {subject}, cameras {_names(sorted(bad))}: camera {name} has tangential coefficients "
        f"p1 = {bad[name][0]:.3g}, p2 = {bad[name][1]:.3g}, beyond a real lens's (|p| < {TANGENTIAL_MAX}): "
        "coefficients in another order? — give them in OpenCV's order k1 k2 p1 p2 k3"
    )
    return [Finding("lens", "dataset", message)] if len(bad) >= SUBJECT_SHARE * len(cameras) else []


def check_subject(task, template, accepted: tuple[str, ...]) -> list[Finding]:
    """Every check that needs no pixel, on one subject: ``task`` a
    :class:`~relightanyone.ingest.subject_task.SubjectTask` (views and the alignment of each frame),
    ``template`` its :class:`~relightanyone.ingest.tracking.Template`."""
    plan = task.plan
    head_mask = ~template.neck_vertices if (~template.neck_vertices).sum() >= 3 else slice(None)
    views_by_frame: dict[int, dict[str, list[SourceView]]] = {}
    for view in plan.views:
        views_by_frame.setdefault(view.frame, {}).setdefault(view.camera.name, []).append(view)
    cases, extents, centres, heads, residuals = [], [], [], [], {}
    items_by_frame: dict[int, list[str]] = {}
    tracked_extent = 0.0
    for frame, alignment in sorted(task.alignments.items()):
        tracked = alignment.tracked_vertices
        if tracked is None:
            continue
        head = tracked[head_mask]
        canonical = transform_points(alignment.canonical_from_tracker, head)
        native = head_in_native(subsample(head), alignment.tracker_from_native)
        extents.append(extent(canonical))
        tracked_extent = extent(head)
        residuals[frame] = alignment.fit_rms_mm
        native_to_m = decompose_similarity(alignment.canonical_from_native)[0]
        for camera, views in views_by_frame.get(frame, {}).items():
            items = tuple(view_item(v) for v in views)
            items_by_frame.setdefault(frame, []).extend(items)
            cam = views[0].camera
            w2c = np.asarray(cam.w2c, np.float64)
            cases.append(
                CameraCase(items, camera, np.asarray(cam.K, np.float64), w2c, cam.width, cam.height, native)
            )
            centres.append(-w2c[:3, :3].T @ w2c[:3, 3])
            heads.append(native.mean(axis=0))
    if not cases:
        return []
    reference_extent = extent(template.vertices[head_mask])
    findings = lens_findings(plan.views, plan.subject, accepted)
    findings += template_findings(plan.subject, template.path, task.template_fit, accepted)
    findings += fit_findings(
        plan.subject, residuals, items_by_frame, tracked_extent, reference_extent, accepted
    )
    sizes = size_findings(
        plan.subject, float(np.median(extents)), np.asarray(centres), np.asarray(heads), native_to_m, accepted
    )
    findings += sizes
    if not sizes:  # with a head of the wrong size, where it projects says nothing more
        # A rig that does not surround the head explains whatever the views show.
        findings += surround_findings(cases, plan.subject, accepted) or camera_findings(
            cases, plan.subject, accepted
        )
    return findings


def check_tasks(tasks, template, accepted: tuple[str, ...] = ()) -> CheckReport:
    """:func:`check_subject` of every task (the views quarantined go to their task's ``refused_views``)."""
    accepted = checked_names(accepted)
    report = CheckReport(accepted=accepted)
    for task in tasks:
        report.findings += check_subject(task, template, accepted)
    return report
