"""The image check (``silhouette``): does the tracked head, projected by each view's camera, lie on the
image's own foreground?

Each ``full`` image is subsampled to at most :data:`SILHOUETTE_SIDE` pixels; its background is the colour
of its border (a studio backdrop), and the foreground what differs from it. A view agrees when most of
the neck-cut head lies on the foreground, or (skin in black shadow) when the foreground lies on the whole
mesh's silhouette. A view that does not is tried flipped, with its camera read in the alternative
conventions of the camera checks (:mod:`.checks`) and with every other camera of its frame, and the
reading that explains it is named, and a view that agrees poorly is tried with the nearest frames' meshes
(:func:`best_other_frame`). :mod:`.image_decisions` judges a subject's views together. Thresholds are
listed in ``docs/ingest.md`` ("Checks").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

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
# Another frame's mesh explains an image when it agrees at least ALTERNATIVE_AGREEMENT and FRAME_GAIN
# better than the view's own frame's.
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
        f"{floor_percent(share)} of the projected head on the image's foreground, overlap "
        f"{floor_percent(overlap)}"
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
        f"{stated}: at best {floor_percent(share)} agree (at least {ON_FOREGROUND:.0%} expected) — another "
        "frame's image, a wrong calibration of this camera, or the head hidden?",
    )


def floor_percent(value: float) -> str:
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
