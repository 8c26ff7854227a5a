"""The image check over one subject's views (:class:`ImageCheck`, in an ingest task or ``doctor``): each
view is judged by :func:`~relightanyone.ingest.image_check.check_view_image`, then the subject's verdicts
are decided together. Frames are compared with each other, images of other frames and the colour order
(``colour-order``) are found from many views, and a subject, frame or camera is refused as a whole when one
mistake shows in all its views. Thresholds are listed in ``docs/ingest.md`` ("Checks").
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np

from relightanyone.align.geometry import invert_similarity
from relightanyone.ingest.checks import CAMERA_ALTERNATIVES, SUBJECT_SHARE, view_item
from relightanyone.ingest.decode import apply_colour_calibration
from relightanyone.ingest.image_check import (
    FRAME_MARGIN,
    SUSPECT_ON_FOREGROUND,
    FrameShape,
    ViewVerdict,
    best_other_frame,
    check_view_image,
    floor_percent,
)
from relightanyone.ingest.records import SourceView

MIN_SUBJECT_VIEWS = 4  # judged views a subject needs before its silhouette failures refuse it as a whole
FRAMES_TRIED = 6  # a held view is tried with the meshes of up to this many nearest frames
# Colour order: on a head under white light red is above blue (skin, lips, brown and black hair). When it is
# the other way round in COLOUR_ORDER_SHARE of a subject's judged views (at least MIN_SUBJECT_VIEWS), by
# BLUE_OVER_RED, the images are in BGR order. Only display-referred images are judged: a raw sensor's
# camera RGB (DNG) or scene-linear EXR need not be white-balanced.
COLOUR_ORDER_SHARE = 0.9
BLUE_OVER_RED = 1.1
COLOUR_ORDER_UNJUDGED_CODECS = ("dng-raw", "exr-linear")
FRAME_MISMATCH = "the tracked mesh disagrees with the frame's images"


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
    out = {}
    for view in views:
        if view.camera.name not in out:
            out[view.camera.name] = (
                np.asarray(view.camera.K, np.float64),
                canonical_w2c(view.camera.w2c, canonical_from_native),
                view.camera.width,
                view.camera.height,
            )
    return out


def canonical_w2c(w2c_native: np.ndarray, canonical_from_native: np.ndarray) -> np.ndarray:
    """``(4, 4)`` a native ``w2c_native`` as a map from canonical space to the camera (native units):
    ``w2c_native · canonical_from_native⁻¹``."""
    return np.asarray(w2c_native, np.float64) @ invert_similarity(canonical_from_native)


class ImageCheck:
    """The image checks (``silhouette``, ``colour-order``) over one subject's views (an ingest task,
    ``doctor``).

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
            canonical_from_native = self.task.alignments[view.frame].canonical_from_native
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
                (meaning, fix, K_alt, canonical_w2c(w2c_alt, canonical_from_native))
                for meaning, fix, K_alt, w2c_alt in changed
            ]

        verdict = check_view_image(
            view.camera.name, image, camera[0], camera[1], self.shapes[view.frame], cameras, conventions
        )
        if verdict.share is None:
            return False
        if verdict.head_rgb is not None and view.image.codec not in COLOUR_ORDER_UNJUDGED_CODECS:
            self._head_colours.setdefault(id(view.colour), (view.colour, []))[1].append(verdict.head_rgb)
        if not self.enabled:
            return False
        # Tried even when a flip, a convention or another camera explains the view: when frames are
        # mispaired, most of a frame's views show the same other frame, and that outvotes chance fits.
        if verdict.share < SUSPECT_ON_FOREGROUND:
            other = best_other_frame(image, camera[0], camera[1], self.shapes[view.frame], self._frames(view))
            verdict = replace(verdict, other_frame=other)
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
        return [
            (f, self.shapes[f], canonical_w2c(view.camera.w2c, self.task.alignments[f].canonical_from_native))
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
                    f"head of frame {other} ({floor_percent(verdict.share)} of the projected head on the "
                    f"image's foreground, {floor_percent(score)} with frame {other}'s mesh): an image from "
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
