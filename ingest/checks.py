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

import cv2
import numpy as np

from relightanyone.align.geometry import (
    decompose_similarity,
    invert_similarity,
    transform_points,
)
from relightanyone.errors import InputError
from relightanyone.ingest.records import SourceView
from relightanyone.ingest.steps import MeshSilhouette

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
MIN_SUBJECT_VIEWS = 4  # judged views a subject needs before its silhouette failures refuse it as a whole
FRAME_MISMATCH = "the tracked mesh disagrees with the frame's images"
EXPLAINED_SHARE = 0.9  # an alternative explains a failure when this share of the views then passes
HEAD_POINTS = 200  # vertices used for the camera checks (evenly subsampled)

# The image check (silhouette): the image is subsampled to at most SILHOUETTE_SIDE pixels on its larger
# side; the background is the colour of the image's border away from the projected head, used only when
# that border is uniform (black, a backdrop); otherwise the check cannot tell and says nothing.
SILHOUETTE_SIDE = 48
OUTLINE_AGREEMENT = 0.9  # ... or at least this share of the foreground on the whole mesh's silhouette
ON_FOREGROUND = 0.8  # share of the projected head (neck cut) that must lie on the foreground
# Below this a view is set aside until the subject's frames can be compared: a frame whose median share is
# below it and FRAME_MARGIN under the subject's typical frame has the mesh of another frame or pose.
SUSPECT_ON_FOREGROUND = 0.97
FRAME_MARGIN = 0.03
ALTERNATIVE_AGREEMENT = 0.9  # an alternative (flip, another camera) explains the image from this agreement
ALTERNATIVE_GAIN = 0.15  # ... and when it is this much better than the view as given
FLIP_OVERLAP = 0.8  # a flipped image explains a view when the mesh's outline overlaps its foreground so
FLIP_SHARE_GAIN = 0.08  # ... or when turning it back puts this much more of the head on the foreground
FLIP_OUTLINE_GAIN = 0.02  # ... and improves the outline's overlap by this much
MIN_MASK_PIXELS = 12  # fewer projected pixels than this: too small to judge
BORDER_BACKGROUND_SHARE = 0.5  # ... of the whole border, when the border away from the head is not uniform
BORDER_UNIFORM = 0.04  # border pixels within this of their median (relative to the image's peak): uniform
# Foreground: farther from the background than this share of the image's peak, and than this many times
# the border's own spread (its noise), whichever is more (dark skin and hair are a few % of the peak).
FOREGROUND_CONTRAST = 0.01
BACKGROUND_NOISE_FACTOR = 4.0


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


# ----------------------------------------------------------------------------------------- image check
def image_foreground(image: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """``(h, w)`` bool foreground of a subsampled ``image (h, w, 3)`` against the colour of its border away
    from ``mask (h, w)`` (the projected head, dilated); None when that border is not uniform."""
    h, w = mask.shape
    ring = np.zeros((h, w), dtype=bool)
    ring[:2], ring[-2:], ring[:, :2], ring[:, -2:] = True, True, True, True
    near = cv2.dilate(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    peak = quantile(channel_max(image).ravel(), 0.99)
    if peak <= 0:
        return None
    estimate = _uniform_background(image[ring & ~near], peak, 0.8)
    if estimate is None:
        # The head may reach the border where the mesh says it does not (a flipped image, another
        # camera's view): then the background is the colour most of the whole border has.
        estimate = _uniform_background(image[ring], peak, BORDER_BACKGROUND_SHARE)
    if estimate is None:
        return None
    background, noise = estimate
    threshold = max(FOREGROUND_CONTRAST * peak, BACKGROUND_NOISE_FACTOR * noise)
    return channel_max(cv2.absdiff(image, np.full_like(image, background))) > threshold


def _uniform_background(border: np.ndarray, peak: float, share: float) -> tuple[np.ndarray, float] | None:
    """``(colour (3,), noise)`` of the background when the ``share`` quantile of the ``border (N, 3)``
    pixels' distance to their median colour (the noise) is within :data:`BORDER_UNIFORM` of the image's
    ``peak``, else None."""
    if len(border) < 16:
        return None
    middle = (len(border) - 1) // 2
    background = np.partition(border, middle, axis=0)[middle].astype(np.float32)  # per-channel median
    noise = quantile(np.abs(border - background).max(axis=1), share)
    return None if noise > BORDER_UNIFORM * peak else (background, noise)


def channel_max(image: np.ndarray) -> np.ndarray:
    """``(h, w)`` the largest of the three channels of ``image (h, w, 3)`` (``max(axis=2)`` is several times
    slower on small images)."""
    return np.maximum(np.maximum(image[..., 0], image[..., 1]), image[..., 2])


def quantile(values: np.ndarray, q: float) -> float:
    """The ``q`` quantile of ``values (N,)`` (the nearest rank below; cheaper than ``np.percentile``)."""
    rank = int(q * (len(values) - 1))
    return float(np.partition(values, rank)[rank])


def hull_vertices(points: np.ndarray) -> np.ndarray:
    """The vertices of the 3D convex hull of ``points (N, 3)``: a perspective projection keeps segments
    straight, so the 2D hull of their projections is the 2D hull of every point's (the whole mesh's
    outline, exactly); an evenly spaced subsample misses the extreme vertices (the chin, the crown) and
    outlines only 73-88 % of a head's silhouette."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # fewer than 4 points, or all in one plane
        return points


def hull_mask(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(h, w)`` bool: the convex hull of ``points (N, 3)`` (those in front of the camera) projected by
    ``K``, ``w2c``; size ``(w, h)``. The outline of a whole head and neck, for comparing shapes."""
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    cam = cam[cam[:, 2] > 0]
    mask = np.zeros((size[1], size[0]), np.uint8)
    if len(cam) >= 3:
        pixels = cam[:, :2] / cam[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
        pixels = np.clip(pixels, -4 * max(size), 4 * max(size))
        hull = cv2.convexHull(np.round(pixels).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def subsampled_camera(K: np.ndarray, stride: int) -> np.ndarray:
    """``K`` of an image subsampled by taking every ``stride``-th pixel (pixel ``i`` of it is ``i · stride``)."""
    out = K.astype(np.float64).copy()
    out[:2] /= stride
    out[2] = K[2]
    return out


def silhouette_stride(width: int, height: int) -> int:
    return max(1, math.ceil(max(width, height) / SILHOUETTE_SIDE))


def overlap_ratio(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two ``(h, w)`` bool masks (0 when both are empty)."""
    union = int(np.count_nonzero(a | b))
    return float(np.count_nonzero(a & b)) / union if union else 0.0


def on_foreground(foreground: np.ndarray, mask: np.ndarray) -> float | None:
    pixels = int(mask.sum())
    if pixels < MIN_MASK_PIXELS:
        return None
    return float(np.count_nonzero(foreground & mask)) / pixels


def foreground_on_outline(foreground: np.ndarray, whole: np.ndarray) -> float:
    """Share of the image's ``foreground (h, w)`` bool that lies on the whole mesh's outline ``whole (h,
    w)``: the other direction of the agreement, blind to skin in deep shadow (as black as a black
    backdrop, so off the foreground), which the head's share on the foreground is not."""
    pixels = int(np.count_nonzero(foreground))
    return float(np.count_nonzero(foreground & whole)) / pixels if pixels else 0.0


@dataclass(frozen=True)
class FrameShape:
    """A frame's tracked mesh as the image check sees it: the exact ``silhouette`` (a
    :class:`~relightanyone.ingest.steps.MeshSilhouette`, neck cut), the exact silhouette of the whole
    mesh ``full`` (neck included), and, for a cheap outline, the vertices of its 3D convex hull ``whole``
    ``(N, 3)``; canonical space."""

    silhouette: object
    whole: np.ndarray
    full: object

    @classmethod
    def of(cls, silhouette) -> FrameShape:
        full = MeshSilhouette(silhouette.vertices, silhouette.faces, method=silhouette.method)
        return cls(silhouette, hull_vertices(silhouette.vertices), full)


@dataclass(frozen=True)
class ViewVerdict:
    """The image check of one view: ``share`` of the projected head on the foreground (None: the
    background is not uniform enough to tell); ``problem`` the reason it fails, ``explained`` when a flip or
    another camera's view explains it."""

    camera: str
    share: float | None
    problem: str | None = None
    explained: bool = False
    swapped_with: str | None = None  # the camera whose view the image shows


def check_view_image(
    camera: str,
    image: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    shape: FrameShape,
    others: dict[str, tuple[np.ndarray, np.ndarray, int, int]],
    conventions: Callable[[], list[tuple[str, str, np.ndarray, np.ndarray]]] | None = None,
) -> ViewVerdict:
    """Does the head projected by ``K (3, 3)``, ``w2c (4, 4)`` (canonical) lie on the foreground of ``image
    (H, W, 3)``? ``shape`` is the frame's mesh (:class:`FrameShape`);
    ``others`` the frame's other cameras ``name -> (K, w2c, width, height)``, tried when the view fails
    (its image may be theirs), after ``conventions()``: this camera read with each of
    :data:`CAMERA_ALTERNATIVES`, ``(meaning, fix, K, w2c)``."""
    height, width = image.shape[:2]
    stride = silhouette_stride(width, height)
    small = np.ascontiguousarray(image[::stride, ::stride, :3], dtype=np.float32)
    size = (small.shape[1], small.shape[0])
    K_small = subsampled_camera(K, stride)
    # The whole mesh's outline (neck included; the convex hull of a few vertices) keeps the background
    # estimate off the head and is what a flip is judged by; the share is the exact silhouette's.
    silhouette = shape.silhouette
    whole = hull_mask(shape.whole, K_small, w2c, size)
    foreground = image_foreground(small, whole)
    if foreground is None:
        return ViewVerdict(camera, None)
    head = silhouette.mask(K_small, w2c, size)
    share = on_foreground(foreground, head)
    if share is None:
        return ViewVerdict(camera, share)
    # The whole mesh's outline against the foreground, as given and flipped: a flip shows as a much
    # better overlap, even where the neck-cut head still lies on the foreground.
    overlap = overlap_ratio(foreground, whole)
    stated = (
        f"{_floor_percent(share)} of the projected head on the image's foreground, overlap "
        f"{_floor_percent(overlap)}"
    )
    flips = {
        "upside down": foreground[::-1, ::-1],
        "flipped vertically": foreground[::-1],
        "mirrored left-right": foreground[:, ::-1],
    }
    if foreground.shape[0] == foreground.shape[1]:  # a square image keeps its size when turned a quarter
        flips["rotated 90° clockwise"] = np.rot90(foreground, 1)  # turned back counter-clockwise
        flips["rotated 90° counter-clockwise"] = np.rot90(foreground, -1)
    if overlap > 1.0 - ALTERNATIVE_GAIN and share >= SUSPECT_ON_FOREGROUND:
        flips = {}  # no flip can do better
    for what, flipped in flips.items():
        score = overlap_ratio(flipped, whole)
        # A much better outline; or, when the head is framed so that its outline changes little under a
        # flip, the head lying wholly on the foreground once turned back (and the outline better too).
        if (score >= FLIP_OVERLAP and score >= overlap + ALTERNATIVE_GAIN) or (
            share < SUSPECT_ON_FOREGROUND
            and score >= overlap + FLIP_OUTLINE_GAIN
            and (on_foreground(flipped, head) or 0.0) >= max(ALTERNATIVE_AGREEMENT, share + FLIP_SHARE_GAIN)
        ):
            return ViewVerdict(
                camera,
                share,
                f"the image of camera {camera} is {what} relative to its mask ({stated}; {score:.0%} "
                "with the image turned back) — fix the image's orientation",
                True,
            )
    if share >= ON_FOREGROUND:
        return ViewVerdict(camera, share)
    # Part of the head is off the foreground: shadowed skin, or the wrong camera or image. Another reading
    # that puts the head clearly better on the foreground names the mistake; otherwise the view agrees when
    # its foreground lies on the head's outline (the shadow case), and is judged by the larger share.
    # The whole mesh's exact silhouette, not its convex hull: a hull would also take in much of the
    # foreground of another frame's or camera's image.
    outline = foreground_on_outline(foreground, shape.full.mask(K_small, w2c, size))
    if outline >= OUTLINE_AGREEMENT:
        share = max(share, outline)

    def agreement(K_alt: np.ndarray, w2c_alt: np.ndarray) -> tuple[float, float]:
        """(share, outline overlap) of the head seen by another camera on this image's foreground, judged
        both ways as the view itself; the share (an exact silhouette, the costly part) only when the
        outline overlaps the foreground clearly better than as given (relative: in deep shadow no outline
        overlaps the foreground well)."""
        K_alt = subsampled_camera(K_alt, stride)
        alt_whole = hull_mask(shape.whole, K_alt, w2c_alt, size)
        alt_overlap = overlap_ratio(foreground, alt_whole)
        if alt_overlap < overlap + ALTERNATIVE_GAIN:
            return 0.0, alt_overlap
        alt_share = on_foreground(foreground, silhouette.mask(K_alt, w2c_alt, size)) or 0.0
        return max(alt_share, foreground_on_outline(foreground, alt_whole)), alt_overlap

    def explains(scores: tuple[float, float]) -> bool:
        return scores[0] >= ALTERNATIVE_AGREEMENT  # its outline gained already (else the share is 0)

    for meaning, fix, K_alt, w2c_alt in conventions() if conventions is not None else ():
        scores = agreement(K_alt, w2c_alt)
        if explains(scores):
            return ViewVerdict(
                camera,
                share,
                f"camera {camera}: {stated}; {meaning} (changed so, {scores[0]:.0%} of it on the foreground) "
                f"— {fix}",
                True,
            )
    best: tuple[float, str] | None = None
    for other, (K_o, w2c_o, w_o, h_o) in others.items():
        if other == camera or (w_o, h_o) != (width, height):
            continue
        scores = agreement(K_o, w2c_o)
        if explains(scores) and (best is None or scores[0] > best[0]):
            best = (scores[0], other)
    if best is not None:
        return ViewVerdict(
            camera,
            share,
            f"the image of camera {camera} shows camera {best[1]}'s view ({stated}, {best[0]:.0%} with "
            f"{best[1]}'s camera): views of cameras {camera} and {best[1]} look swapped — check the "
            "image names",
            True,
            best[1],
        )
    if share >= ON_FOREGROUND:
        return ViewVerdict(camera, share)
    return ViewVerdict(
        camera,
        share,
        f"{stated}: at best {_floor_percent(share)} agree (at least {ON_FOREGROUND:.0%} expected) — another "
        "frame's image, a wrong calibration of this camera, or the head hidden?",
    )


def _floor_percent(value: float) -> str:
    """``value`` in [0, 1] as a whole percentage rounded down, so a share under a threshold never reads as
    the threshold."""
    return f"{math.floor(value * 100 + 1e-9)}%"


def mismatched_frames(shares_by_frame: dict[int, list[float]]) -> tuple[dict[int, float], float]:
    """Frames whose views agree with their tracked mesh clearly worse than the subject's other frames:
    ``({frame: median share}, the subject's median of frame medians)``. Needs two frames with at least two
    judged views each (a single frame has nothing to be compared with)."""
    medians = {f: float(np.median(s)) for f, s in shares_by_frame.items() if len(s) >= 2}
    if len(medians) < 2:
        return {}, float("nan")
    baseline = float(np.median(list(medians.values())))
    bad = {f: m for f, m in medians.items() if m < SUSPECT_ON_FOREGROUND and m < baseline - FRAME_MARGIN}
    return bad, baseline


def _most_frequent(problems: list[str]) -> str:
    """The most frequent of ``problems`` without its ``subject … frame …:`` prefix."""
    stripped = [p.split(": ", 1)[1] if p.startswith("subject ") and ": " in p else p for p in problems]
    return max(sorted(set(stripped)), key=stripped.count)


def view_item(view: SourceView) -> str:
    """The quarantine item of a view: ``subject/frame/camera/pattern``."""
    return f"{view.subject}/{view.frame:06d}/{view.camera.name}/{view.pattern}"


def frame_cameras(
    views: Iterable[SourceView], canonical_from_native: np.ndarray
) -> dict[str, tuple[np.ndarray, np.ndarray, int, int]]:
    """camera -> ``(K, w2c, width, height)`` of one frame's views, ``w2c`` from canonical space to camera
    coordinates in native units, ``w2c_native · canonical_from_native⁻¹``: the pixels of
    :func:`~relightanyone.align.geometry.w2c_to_canonical`, which also rescales the camera to metres and
    re-orthonormalises it for storage (a projection needs neither)."""
    native_from_canonical = invert_similarity(canonical_from_native)
    out = {}
    for view in views:
        if view.camera.name not in out:
            w2c = np.asarray(view.camera.w2c, np.float64) @ native_from_canonical
            out[view.camera.name] = (
                np.asarray(view.camera.K, np.float64),
                w2c,
                view.camera.width,
                view.camera.height,
            )
    return out


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


class ImageCheck:
    """The silhouette check over one subject's views (an ingest task, ``doctor``).

    A view that fails, or agrees with its mesh less than :data:`SUSPECT_ON_FOREGROUND`, is held back (no
    row) until every view was seen; then the frames are compared (:func:`mismatched_frames`): held views of
    a mismatched frame, and views that fail, are refused with their reason, the others are released and
    written after all. ``silhouettes``: frame -> the frame's
    :class:`~relightanyone.ingest.steps.MeshSilhouette` in canonical space. Only ``"full"`` images are
    judged (an OLAT image lights part of the head).
    """

    def __init__(self, task, silhouettes: dict, accepted: tuple[str, ...] = ()):
        self.task = task
        self.shapes = {frame: FrameShape.of(silhouette) for frame, silhouette in silhouettes.items()}
        self.enabled = "silhouette" not in accepted
        self._views: dict[int, list[SourceView]] = {}
        for view in task.plan.views:
            self._views.setdefault(view.frame, []).append(view)
        self._cameras: dict[int, dict] = {}
        self._shares: dict[int, list[float]] = {}
        self._held: list[tuple[SourceView, str, ViewVerdict]] = []
        self._released: set[str] = set()
        self._refusals: list[tuple[str, str, str]] = []
        self._swaps: dict[tuple[int, str], str] = {}  # (frame, camera) -> the problem its partner named
        self._judged: dict[str, int] = {}  # camera -> views judged
        self._withdrawn: dict[str, str] = {}  # camera (or "" for the whole subject) -> reason

    def holds(self, view: SourceView, item: str, image: np.ndarray) -> bool:
        """Judge ``image (H, W, 3)`` of ``view``; True when it is held back."""
        if not self.enabled or view.pattern != "full" or view.frame not in self.shapes:
            return False
        if item in self._released:
            return False
        if view.frame not in self._cameras:
            alignment = self.task.alignments[view.frame]
            self._cameras[view.frame] = frame_cameras(
                self._views[view.frame], alignment.canonical_from_native
            )
        cameras = self._cameras[view.frame]
        camera = cameras.get(view.camera.name)
        if camera is None or image.shape[:2] != (camera[3], camera[2]):
            return False  # not rigid or the wrong size: other steps refuse it with that reason

        def conventions() -> list[tuple[str, str, np.ndarray, np.ndarray]]:
            """This camera read with each alternative convention, as canonical cameras (only on failure)."""
            native_from_canonical = invert_similarity(self.task.alignments[view.frame].canonical_from_native)
            K, w2c, width, height = (
                view.camera.K,
                np.asarray(view.camera.w2c),
                view.camera.width,
                view.camera.height,
            )
            changed = [
                (meaning, fix, *change(K, w2c, width, height)) for meaning, fix, change in CAMERA_ALTERNATIVES
            ]
            return [
                (meaning, fix, K_alt, w2c_alt @ native_from_canonical)
                for meaning, fix, K_alt, w2c_alt in changed
            ]

        verdict = check_view_image(
            view.camera.name, image, camera[0], camera[1], self.shapes[view.frame], cameras, conventions
        )
        if verdict.share is None:
            return False
        self._shares.setdefault(view.frame, []).append(verdict.share)
        self._judged[view.camera.name] = self._judged.get(view.camera.name, 0) + 1
        if verdict.swapped_with is not None:
            self._swaps[(view.frame, verdict.swapped_with)] = verdict.problem
        swapped = self._swaps.get((view.frame, view.camera.name))
        if swapped is not None and not verdict.explained:
            verdict = ViewVerdict(verdict.camera, verdict.share, swapped, True)
        if verdict.problem is None and verdict.share >= SUSPECT_ON_FOREGROUND:
            return False
        self._held.append((view, item, verdict))
        return True

    def decide(self) -> tuple[list[tuple[str, str, str]], list[SourceView]]:
        """After every view was judged: ``(item, source, reason)`` of the held views to refuse, and the
        held views to release. Failures on more than :data:`SUBJECT_SHARE` of the subject's judged views
        refuse the whole subject, and a camera whose views all fail or agree poorly (at least half fail)
        is refused as a whole: one wrong calibration or a tracking of other images shows in every view,
        whatever each view's own verdict guessed (:meth:`withdrawn` then names the views already
        written)."""
        refusals, released = self._view_decisions()
        judged = sum(self._judged.values())
        problems = {item: reason for item, _, reason in refusals}
        if judged >= MIN_SUBJECT_VIEWS and len(problems) > SUBJECT_SHARE * judged:
            reason = self._subject_reason(len(problems), judged, list(problems.values()))
            self._withdrawn = {"": reason}
            return [(item, view.source, reason) for view, item, _ in self._held], []
        by_camera: dict[str, list[str]] = {}
        for view, item, _ in self._held:
            by_camera.setdefault(view.camera.name, []).append(item)
        for camera, items in by_camera.items():
            failing = [problems[i] for i in items if i in problems and FRAME_MISMATCH not in problems[i]]
            # Every judged view of the camera was held (none agreed well) and at least half failed.
            if (
                len(items) >= 2
                and len(items) == self._judged.get(camera, 0)
                and 2 * len(failing) >= len(items)
            ):
                self._withdrawn[camera] = self._camera_reason(camera, len(failing), len(items), failing)
        if self._withdrawn:
            camera_of = {item: view.camera.name for view, item, _ in self._held}
            refusals = [
                (item, source, self._withdrawn.get(camera_of[item], reason))
                for item, source, reason in refusals
            ]
            refusals += [
                (view_item(v), v.source, self._withdrawn[v.camera.name])
                for v in released
                if v.camera.name in self._withdrawn
            ]
            released = [v for v in released if v.camera.name not in self._withdrawn]
        return refusals, released

    def withdrawn(self) -> dict[str, str]:
        """After :meth:`decide`: item -> reason of every view of the subject (any pattern, any frame) that
        a subject- or camera-wide failure refuses, including views already written."""
        if not self._withdrawn:
            return {}
        whole = self._withdrawn.get("")
        return {
            view_item(v): whole or self._withdrawn[v.camera.name]
            for v in self.task.plan.views
            if whole is not None or v.camera.name in self._withdrawn
        }

    def _subject_reason(self, failing: int, judged: int, problems: list[str]) -> str:
        subject = self.task.plan.subject
        shares = [s for frame in self._shares.values() for s in frame]
        return (
            f"subject {subject}: {failing} of {judged} judged views disagree with the tracked mesh (median "
            f"{float(np.median(shares)):.0%} of the projected head on the image's foreground), so every view "
            "of the subject is refused: the tracking is not of these images (another sequence: --sequence; "
            "another subject) or the whole rig's calibration is read wrongly; most frequent view finding: "
            f"{_most_frequent(problems)}"
        )

    def _camera_reason(self, camera: str, failing: int, held: int, problems: list[str]) -> str:
        return (
            f"subject {self.task.plan.subject} camera {camera}: {failing} of its {held} judged views fail and "
            "none agrees well with the tracked mesh, so all its views are refused: a fault of the camera "
            f"itself (its calibration, or the names of its images) — fix camera {camera}; most frequent "
            f"finding: {_most_frequent(problems)}"
        )

    def _view_decisions(self) -> tuple[list[tuple[str, str, str]], list[SourceView]]:
        """:meth:`decide` for each held view on its own."""
        subject = self.task.plan.subject
        bad, baseline = mismatched_frames(self._shares)
        refusals, released = [], []
        for view, item, verdict in self._held:
            swapped = self._swaps.get((view.frame, view.camera.name))
            if swapped is not None and not verdict.explained:
                verdict = ViewVerdict(verdict.camera, verdict.share, swapped, True)
            if verdict.explained:
                refusals.append(
                    (item, view.source, f"subject {subject} frame {view.frame}: {verdict.problem}")
                )
            elif view.frame in bad:
                refusals.append(
                    (
                        item,
                        view.source,
                        f"subject {subject} frame {view.frame}: {FRAME_MISMATCH} "
                        f"(median {bad[view.frame]:.0%} of the projected head on the foreground, "
                        f"{baseline:.0%} in the subject's frames): the mesh of another frame or head pose? "
                        "— check the tracking's frame numbers",
                    )
                )
            elif verdict.problem is not None:
                refusals.append(
                    (item, view.source, f"subject {subject} frame {view.frame}: {verdict.problem}")
                )
            else:
                released.append(view)
        return refusals, released

    def passes(self, views: list[SourceView], before_release: Callable[[list], None] | None = None):
        """Every view of ``views``, then the held views that :meth:`decide` releases (judged once), after
        ``before_release`` of their images (the task's decoder prefetches video frames in one pass)."""
        yield from views
        self._refusals, released = self.decide()
        self._released = {view_item(v) for v in released}
        if released and before_release is not None:
            before_release([v.image for v in released])
        yield from released

    def refusals(self) -> list[tuple[str, str, str]]:
        """``(item, source, reason)`` of the views refused, once :meth:`passes` is exhausted."""
        return self._refusals
