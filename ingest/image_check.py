"""The image check (``silhouette``): does the tracked head, projected by each view's camera, lie on the
image's own foreground?

Each ``full`` image is subsampled to at most :data:`SILHOUETTE_SIDE` pixels; its background is the colour
of its border (a studio backdrop), and the foreground what differs from it. A view agrees when most of
the neck-cut head lies on the foreground, or (skin in black shadow) when the foreground lies on the whole
mesh's silhouette. A view that does not is tried flipped, with its camera read in the alternative
conventions of the camera checks (:mod:`.checks`) and with every other camera of its frame, and the
reading that explains it is named. :class:`ImageCheck` judges one subject's views in an ingest task or in
``doctor``: it compares the frames, and refuses a subject or a camera as a whole when their failures
concern more than one view. Thresholds are listed in ``docs/ingest.md`` ("Checks").
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from relightanyone.align.geometry import invert_similarity
from relightanyone.ingest.checks import CAMERA_ALTERNATIVES, SUBJECT_SHARE, view_item
from relightanyone.ingest.decode import apply_colour_calibration
from relightanyone.ingest.records import SourceView
from relightanyone.ingest.steps import MeshSilhouette

# The image check (silhouette): the image is subsampled to at most SILHOUETTE_SIDE pixels on its larger
# side; the background is the colour of the image's border away from the projected head, used only when
# that border is uniform (black, a backdrop); otherwise the check cannot tell and says nothing.
SILHOUETTE_SIDE = 48
OUTLINE_POINTS = 300  # vertices of the mesh's convex hull that outline it (spread over the hull)
OUTLINE_AGREEMENT = 0.9  # ... or at least this share of the foreground on the whole mesh's silhouette
ON_FOREGROUND = 0.8  # share of the projected head (neck cut) that must lie on the foreground
# Below this a view is set aside until the subject's frames can be compared: a frame whose median share is
# below it and FRAME_MARGIN under the subject's typical frame has the mesh of another frame or pose.
SUSPECT_ON_FOREGROUND = 0.97
FRAME_MARGIN = 0.03
# A held view is also tried with the meshes of up to FRAMES_TRIED nearest frames: one that agrees at least
# ALTERNATIVE_AGREEMENT and FRAME_GAIN better than the view's own frame shows the image is of that frame.
FRAMES_TRIED = 6
FRAME_GAIN = 0.05
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
MIN_SUBJECT_VIEWS = 4  # judged views a subject needs before its silhouette failures refuse it as a whole
# Colour order: on a head under white light red is above blue (skin, lips, brown and black hair). When it is
# the other way round in COLOUR_ORDER_SHARE of a subject's judged views (at least MIN_SUBJECT_VIEWS), by
# BLUE_OVER_RED, the images are in BGR order. Only display-referred images are judged: a raw sensor's
# camera RGB (DNG) or scene-linear EXR need not be white-balanced.
COLOUR_ORDER_SHARE = 0.9
BLUE_OVER_RED = 1.1
COLOUR_ORDER_UNJUDGED_CODECS = ("dng-raw", "exr-linear")
FRAME_MISMATCH = "the tracked mesh disagrees with the frame's images"


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


def hull_indices(points: np.ndarray) -> np.ndarray:
    """``(M,)`` indices of the vertices of the 3D convex hull of ``points (N, 3)`` (all when there is none).
    A perspective projection keeps segments straight, so the 2D hull of their projections is the 2D hull
    of every point's; an evenly spaced subsample misses the extreme vertices (the chin, the crown) and
    outlines only 73-88 % of a head's silhouette."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return ConvexHull(points).vertices
    except (QhullError, ValueError):  # fewer than 4 points, or all in one plane
        return np.arange(len(points))


def spread_indices(points: np.ndarray, count: int) -> np.ndarray:
    """``(min(N, count),)`` indices of ``points (N, 3)`` spread over them: each the farthest from those
    chosen before (the first is index 0)."""
    if len(points) <= count:
        return np.arange(len(points))
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    for _ in range(count - 1):
        chosen.append(int(distance.argmax()))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.asarray(chosen)


# Vertices outlining a topology, found once per topology (the first mesh's) and kept for every frame:
# a head's extreme vertices stay the extreme ones from one expression to the next.
_OUTLINE_VERTICES: dict[tuple, np.ndarray] = {}


def outline_indices(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(M,)`` at most :data:`OUTLINE_POINTS` vertices of the mesh's 3D convex hull, spread over it: their
    projected hull covers about 97 % of the whole mesh's (93 % at worst, at the check's 48 pixels) for a
    fraction of the cost; cached per topology (``faces (F, 3)``)."""
    key = (len(vertices), faces.shape, hash(faces.tobytes()))
    if key not in _OUTLINE_VERTICES:
        hull = hull_indices(vertices)
        _OUTLINE_VERTICES.clear()  # one topology per ingest; do not grow across many
        _OUTLINE_VERTICES[key] = hull[spread_indices(vertices[hull], OUTLINE_POINTS)]
    return _OUTLINE_VERTICES[key]


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


def subsampled_view(image: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``(small (h, w, 3) float32, its K (3, 3), stride)``: ``image (H, W, C)`` subsampled to at most
    :data:`SILHOUETTE_SIDE` pixels on its larger side, as the image check reads it."""
    stride = silhouette_stride(image.shape[1], image.shape[0])
    small = np.ascontiguousarray(image[::stride, ::stride, :3], dtype=np.float32)
    return small, subsampled_camera(K, stride), stride


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
    mesh ``full`` (neck included), and, for a cheap outline, vertices spread over its 3D convex hull ``whole``
    ``(N, 3)``; canonical space."""

    silhouette: object
    whole: np.ndarray
    full: object

    @classmethod
    def of(cls, silhouette) -> FrameShape:
        full = MeshSilhouette(silhouette.vertices, silhouette.faces, method=silhouette.method)
        vertices = silhouette.vertices
        return cls(silhouette, vertices[outline_indices(vertices, silhouette.faces)], full)


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
    other_frame: tuple[int, float] | None = None  # (frame, agreement) of another frame that explains it
    head_rgb: tuple[float, float, float] | None = None  # mean colour of the head on the foreground


def shape_agreement(
    foreground: np.ndarray, shape: FrameShape, K: np.ndarray, w2c: np.ndarray, size: tuple[int, int]
) -> float:
    """How well ``shape`` seen by ``K (3, 3)``, ``w2c (4, 4)`` explains ``foreground (h, w)`` (size ``(w,
    h)``): the share of its head on the foreground, or, when larger and at least
    :data:`OUTLINE_AGREEMENT`, the share of the foreground on its whole silhouette (the shadow case)."""
    head = on_foreground(foreground, shape.silhouette.mask(K, w2c, size)) or 0.0
    outline = foreground_on_outline(foreground, shape.full.mask(K, w2c, size))
    return max(head, outline) if outline >= OUTLINE_AGREEMENT else head


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
    small, K_small, stride = subsampled_view(image, K)
    size = (small.shape[1], small.shape[0])
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
    on_head = (head & foreground).view(np.uint8)
    head_rgb = cv2.mean(small, mask=on_head)[:3] if on_head.any() else None

    def verdict(*args, **kwargs) -> ViewVerdict:
        return ViewVerdict(camera, *args, head_rgb=head_rgb, **kwargs)

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
            return verdict(
                share,
                f"the image of camera {camera} is {what} relative to its mask ({stated}; {score:.0%} "
                "with the image turned back) — fix the image's orientation",
                True,
            )
    if share >= ON_FOREGROUND:
        return verdict(share)
    # Part of the head is off the foreground: shadowed skin, or the wrong camera or image. Another reading
    # that puts the head clearly better on the foreground names the mistake; otherwise the view agrees when
    # nearly all of its foreground lies on the whole mesh's exact silhouette (the shadow case; not its
    # convex hull, which would take in much of another frame's or camera's image), and is judged by the
    # larger share.
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
            return verdict(
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
        return verdict(
            share,
            f"the image of camera {camera} shows camera {best[1]}'s view ({stated}, {best[0]:.0%} with "
            f"{best[1]}'s camera): views of cameras {camera} and {best[1]} look swapped — check the "
            "image names",
            True,
            best[1],
        )
    if share >= ON_FOREGROUND:
        return verdict(share)
    return verdict(
        share,
        f"{stated}: at best {_floor_percent(share)} agree (at least {ON_FOREGROUND:.0%} expected) — another "
        "frame's image, a wrong calibration of this camera, or the head hidden?",
    )


def _floor_percent(value: float) -> str:
    """``value`` in [0, 1] as a whole percentage rounded down, so a share under a threshold never reads as
    the threshold."""
    return f"{math.floor(value * 100 + 1e-9)}%"


def best_other_frame(
    image: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    shape: FrameShape,
    frames: list[tuple[int, FrameShape, np.ndarray]],
) -> tuple[int, float] | None:
    """``(frame, agreement)`` of the other frame whose mesh explains ``image (H, W, 3)`` best, when one
    agrees at least :data:`ALTERNATIVE_AGREEMENT` and :data:`FRAME_GAIN` better than the view's own
    ``shape`` seen by ``K (3, 3)``, ``w2c (4, 4)``, and its outline overlaps the image's foreground better;
    else None. ``frames``: ``(frame, shape, w2c)`` of the
    other frames seen by the same camera (canonical space)."""
    small, K_small, _ = subsampled_view(image, K)
    size = (small.shape[1], small.shape[0])
    whole = hull_mask(shape.whole, K_small, w2c, size)
    foreground = image_foreground(small, whole)
    if foreground is None:
        return None
    # Exact silhouettes (the costly part) only for frames whose outline overlaps the foreground better.
    overlap = overlap_ratio(foreground, whole)
    closer = [
        (frame, frame_shape, frame_w2c)
        for frame, frame_shape, frame_w2c in frames
        if overlap_ratio(foreground, hull_mask(frame_shape.whole, K_small, frame_w2c, size)) > overlap
    ]
    if not closer:
        return None
    given = shape_agreement(foreground, shape, K_small, w2c, size)
    best: tuple[int, float] | None = None
    for frame, frame_shape, frame_w2c in closer:
        score = shape_agreement(foreground, frame_shape, K_small, frame_w2c, size)
        if score >= max(ALTERNATIVE_AGREEMENT, given + FRAME_GAIN) and (best is None or score > best[1]):
            best = (frame, score)
    return best


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
        self.colour_order_enabled = "colour-order" not in accepted
        # id(colour calibration) -> (calibration, the mean colours (3,) of the judged heads it applies to)
        self._head_colours: dict[int, tuple[object, list[tuple[float, float, float]]]] = {}
        self._checks: dict[str, str] = {}  # reason -> the check that gave it, when not "silhouette"
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
        self._withdrawn_frames: dict[int, str] = {}  # frame -> reason

    def holds(self, view: SourceView, item: str, image: np.ndarray) -> bool:
        """Judge ``image (H, W, 3)`` of ``view``; True when it is held back."""
        judging = self.enabled or self.colour_order_enabled
        if not judging or view.pattern != "full" or view.frame not in self.shapes:
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
        # Tried even when a flip, a convention or another camera explains the view: when frames are
        # mispaired, most of a frame's views show the same other frame, and that outvotes chance fits.
        if verdict.share is not None and verdict.share < SUSPECT_ON_FOREGROUND:
            other = best_other_frame(image, camera[0], camera[1], self.shapes[view.frame], self._frames(view))
            verdict = replace(verdict, other_frame=other)
        if verdict.share is None:
            return False
        if verdict.head_rgb is not None and view.image.codec not in COLOUR_ORDER_UNJUDGED_CODECS:
            self._head_colours.setdefault(id(view.colour), (view.colour, []))[1].append(verdict.head_rgb)
        if not self.enabled:
            return False
        self._shares.setdefault(view.frame, []).append(verdict.share)
        self._judged[view.camera.name] = self._judged.get(view.camera.name, 0) + 1
        if verdict.swapped_with is not None:
            self._swaps[(view.frame, verdict.swapped_with)] = verdict.problem
        swapped = self._swaps.get((view.frame, view.camera.name))
        if swapped is not None and not verdict.explained:
            verdict = replace(verdict, problem=swapped, explained=True)
        if verdict.problem is None and verdict.share >= SUSPECT_ON_FOREGROUND:
            return False
        self._held.append((view, item, verdict))
        return True

    def _frames(self, view: SourceView) -> list[tuple[int, FrameShape, np.ndarray]]:
        """``(frame, shape, w2c)`` of the :data:`FRAMES_TRIED` frames nearest ``view``'s, seen by its camera
        (canonical space)."""
        nearest = sorted((f for f in self.shapes if f != view.frame), key=lambda f: (abs(f - view.frame), f))
        w2c_native = np.asarray(view.camera.w2c, np.float64)
        return [
            (f, self.shapes[f], w2c_native @ invert_similarity(self.task.alignments[f].canonical_from_native))
            for f in nearest[:FRAMES_TRIED]
        ]

    def decide(self) -> tuple[list[tuple[str, str, str]], list[SourceView]]:
        """After every view was judged: ``(item, source, reason)`` of the held views to refuse, and the
        held views to release. Failures on more than :data:`SUBJECT_SHARE` of the subject's judged views
        refuse the whole subject, a frame whose images are another frame's is refused as a whole, and a
        camera whose views all fail or agree poorly (at least half fail) is refused as a whole: one wrong
        calibration, pairing or tracking shows in every view, whatever each view's own verdict guessed
        (:meth:`withdrawn` then names the views already written)."""
        colour_order = self._colour_order_reason()
        if colour_order is not None:
            self._checks[colour_order] = "colour-order"
            self._withdrawn = {"": colour_order}
            return [(item, view.source, colour_order) for view, item, _ in self._held], []
        bad, baseline = mismatched_frames(self._shares)
        # An image of another tracked frame shows that the tracking is of these images, only mispaired.
        of_other_frames, self._withdrawn_frames = self._other_frame_reasons(bad)
        refusals, released = self._view_decisions(bad, baseline, of_other_frames)
        judged = sum(self._judged.values())
        problems = {item: reason for item, _, reason in refusals}
        if judged >= MIN_SUBJECT_VIEWS and len(problems.keys() - of_other_frames) > SUBJECT_SHARE * judged:
            reason = self._subject_reason(len(problems), judged, list(problems.values()))
            self._withdrawn, self._withdrawn_frames = {"": reason}, {}
            return [(item, view.source, reason) for view, item, _ in self._held], []
        by_camera: dict[str, list[str]] = {}
        for view, item, _ in self._held:
            by_camera.setdefault(view.camera.name, []).append(item)
        for camera, items in by_camera.items():
            failing = [
                problems[i]
                for i in items
                if i in problems and i not in of_other_frames and FRAME_MISMATCH not in problems[i]
            ]
            # Every judged view of the camera was held (none agreed well) and at least half failed.
            if (
                len(items) >= 2
                and len(items) == self._judged.get(camera, 0)
                and 2 * len(failing) >= len(items)
            ):
                self._withdrawn[camera] = self._camera_reason(camera, len(failing), len(items), failing)
        held = {item: view for view, item, _ in self._held}
        refusals = [
            (item, source, self._withdrawal(held[item]) or reason) for item, source, reason in refusals
        ]
        refusals += [(view_item(v), v.source, self._withdrawal(v)) for v in released if self._withdrawal(v)]
        return refusals, [v for v in released if not self._withdrawal(v)]

    def _withdrawal(self, view: SourceView) -> str | None:
        """The reason a subject-, frame- or camera-wide failure refuses ``view``, if one does."""
        return (
            self._withdrawn.get("")
            or self._withdrawn_frames.get(view.frame)
            or self._withdrawn.get(view.camera.name)
        )

    def withdrawn(self) -> dict[str, str]:
        """After :meth:`decide`: item -> reason of every view of the subject (any pattern, any frame) that
        a subject-, frame- or camera-wide failure refuses, including views already written."""
        reasons = {view_item(v): self._withdrawal(v) for v in self.task.plan.views}
        return {item: reason for item, reason in reasons.items() if reason is not None}

    def check_of(self, reason: str) -> str:
        """The name of the check (``--accept-check NAME``) that gave ``reason``."""
        return self._checks.get(reason, "silhouette")

    def _colour_order_reason(self) -> str | None:
        """The reason every view of the subject is refused when its heads are bluer than red
        (:data:`COLOUR_ORDER_SHARE` of its judged views, at least :data:`MIN_SUBJECT_VIEWS`), else None."""
        if not self.colour_order_enabled:
            return None
        # Calibrated as the rows are (on the mean colour), once per calibration.
        calibrated = [
            apply_colour_calibration(np.asarray([means], np.float32), calibration)[0]
            for calibration, means in self._head_colours.values()
        ]
        colours = np.concatenate(calibrated) if calibrated else np.zeros((0, 3), np.float32)
        if len(colours) < MIN_SUBJECT_VIEWS:
            return None
        blue_over_red = colours[:, 2] / np.maximum(colours[:, 0], 1e-6)
        bluer = int(np.count_nonzero(blue_over_red > BLUE_OVER_RED))
        if bluer < COLOUR_ORDER_SHARE * len(colours):
            return None
        return (
            f"subject {self.task.plan.subject}: on the head, blue is above red in {bluer} of {len(colours)} "
            f"judged views (median blue/red {float(np.median(blue_over_red)):.2f}; skin and hair under white "
            "light are redder than blue), so every view of the subject is refused: the images look like BGR "
            "(OpenCV's channel order; cv2.imwrite expects BGR arrays) — write them in RGB order, or pass "
            "--accept-check colour-order for a capture under blue light"
        )

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

    def _other_frame_reasons(self, bad: dict[int, float]) -> tuple[dict[str, str], dict[int, str]]:
        """``(item -> reason, frame -> reason)``: the held views whose images another frame's mesh explains
        (:func:`best_other_frame`), and the frames refused as a whole because of them. A frame is when
        most of its judged views show the same other frame, or when that frame's views show it in turn
        (the two exchanged their images); one view alone is refused in a frame that otherwise agrees
        with its mesh (not in ``bad``). A wrong mesh for a frame makes neighbouring frames fit its
        images better too, but neither most of them the same one nor the neighbours' own images."""
        subject = self.task.plan.subject
        votes = Counter((view.frame, v.other_frame[0]) for view, _, v in self._held if v.other_frame)
        frames: dict[int, str] = {}
        for (frame, other), count in sorted(votes.items()):
            judged = len(self._shares[frame])
            exchanged = votes.get((other, frame), 0) > 0
            if (count >= 2 and 2 * count > judged) or exchanged:
                frames[frame] = (
                    f"subject {subject} frame {frame}: {count} of its {judged} judged images show the head "
                    f"of frame {other}"
                    + (f", and frame {other}'s images that of frame {frame}" if exchanged else "")
                    + ": images and tracking are paired with the wrong frames, so every view of the frame is "
                    "refused — check the frame numbers of the image folders and of the tracking"
                )
        reasons = {}
        for view, item, verdict in self._held:
            if view.frame in frames:
                reasons[item] = frames[view.frame]
            elif verdict.other_frame is not None and view.frame not in bad:
                other, score = verdict.other_frame
                reasons[item] = (
                    f"subject {subject} frame {view.frame}: the image of camera {view.camera.name} shows the "
                    f"head of frame {other} ({_floor_percent(verdict.share)} of the projected head on the "
                    f"image's foreground, {_floor_percent(score)} with frame {other}'s mesh): an image from "
                    "another frame — check its file"
                )
        return reasons, frames

    def _view_decisions(
        self, bad: dict[int, float], baseline: float, of_other_frames: dict[str, str]
    ) -> tuple[list[tuple[str, str, str]], list[SourceView]]:
        """:meth:`decide` for each held view on its own."""
        subject = self.task.plan.subject
        refusals, released = [], []
        for view, item, verdict in self._held:
            swapped = self._swaps.get((view.frame, view.camera.name))
            if swapped is not None and not verdict.explained:
                verdict = replace(verdict, problem=swapped, explained=True)
            if item in of_other_frames:
                refusals.append((item, view.source, of_other_frames[item]))
            elif verdict.explained:
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
