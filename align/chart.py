"""ColorChecker 24 detection (OpenCV ``mcc``) and chart-based colour-matrix fitting.

Reference: the X-Rite ColorChecker 24 "After November 2014" measurements shipped with colour-science
(xyY under CIE D50). We express them as **linear sRGB under D65**, chromatically adapted with CAT02, so a
camera white-balanced to the scene illuminant sees neutral patches as R = G = B. See ``docs/align.md``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

# ``colour`` is colour-science, imported by align.colour with its plotting warning silenced.
from relightanyone.align.colour import ColourError, ccm_error, colour, fit_ccm, linear_to_srgb

COLORCHECKER_NAME = "ColorChecker24 - After November 2014"
COLORCHECKER_PATCHES = 24
# Fraction of each detected patch quad kept around its centre when averaging, to stay off the edges.
PATCH_SHRINK = 0.7


class ChartNotFoundError(ValueError):
    """No ColorChecker 24 was found in the image."""


@dataclass(frozen=True)
class ChartDetection:
    """A detected ColorChecker 24.

    patch_means: ``(24, 3)`` mean linear RGB of each patch, in the reference chart order (dark skin first,
        black last). patch_quads: ``(24, 4, 2)`` pixel corners of each patch's sampled area.
    chart_quad: ``(4, 2)`` pixel corners of the whole chart. cost: OpenCV mcc fitting cost (lower is better).
    """

    patch_means: np.ndarray
    patch_quads: np.ndarray
    chart_quad: np.ndarray
    cost: float


def reference_colorchecker_linear(whitepoint: str = "D65") -> np.ndarray:
    """Linear sRGB primaries of the ColorChecker 24 (After November 2014), reflectance scale (white ≈ 0.88).

    Args:
        whitepoint: CIE illuminant name the chart is seen under (``"D65"``: the sRGB white, so neutrals map
            to R = G = B). The D50 measurements are adapted to it with CAT02.
    Returns:
        ``(24, 3)`` float64 in chart order (row-major from "dark skin" to "black").
    """
    chart = colour.CCS_COLOURCHECKERS[COLORCHECKER_NAME]
    try:
        illuminant = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"][whitepoint]
    except KeyError as exc:
        raise ValueError(f"unknown CIE illuminant {whitepoint!r} (e.g. 'D65', 'D50')") from exc
    XYZ = colour.xyY_to_XYZ(np.array(list(chart.data.values()), dtype=np.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        XYZ = colour.chromatic_adaptation(
            XYZ,
            colour.xy_to_XYZ(chart.illuminant),
            colour.xy_to_XYZ(illuminant),
            method="Von Kries",
            transform="CAT02",
        )
        srgb = colour.RGB_COLOURSPACES["sRGB"]
        # Adaptation was done above, so convert with the sRGB matrix only (its own white is D65).
        rgb = colour.XYZ_to_RGB(XYZ, srgb, illuminant=srgb.whitepoint, chromatic_adaptation_transform=None)
    return np.asarray(rgb, dtype=np.float64)


def _detection_image_bgr8(image_linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB-encoded BGR copy for the detector, normalised so the 99.5th percentile maps to 1.

    The detector was tuned on display images; the normalisation makes dim linear captures detectable and
    does not affect the patch means, which are read from the linear pixels.
    """
    scale = float(np.percentile(image_linear, 99.5))
    if not np.isfinite(scale) or scale <= 0:
        raise ChartNotFoundError("image is black or not finite; no chart can be detected")
    encoded = linear_to_srgb(np.clip(image_linear / scale, 0.0, 1.0))
    rgb8 = np.clip(np.round(encoded * 255.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(rgb8[..., ::-1])


def _polygon_mean(image: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """Mean ``(3,)`` of the pixels whose centres fall inside convex ``quad (4, 2)``."""
    import cv2

    h, w = image.shape[:2]
    x0 = max(int(np.floor(quad[:, 0].min())), 0)
    y0 = max(int(np.floor(quad[:, 1].min())), 0)
    x1 = min(int(np.ceil(quad[:, 0].max())) + 1, w)
    y1 = min(int(np.ceil(quad[:, 1].max())) + 1, h)
    if x1 <= x0 or y1 <= y0:
        raise ChartNotFoundError(f"detected patch {quad.tolist()} lies outside the {w}×{h} image")
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    # fillConvexPoly with 4 fractional bits: vertices given in 1/16 pixel units.
    pts = np.round((quad - [x0, y0]) * 16).astype(np.int32)
    cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=4)
    selected = image[y0:y1, x0:x1][mask.astype(bool)]
    if selected.shape[0] == 0:
        raise ChartNotFoundError("a detected patch covers no pixel; the chart is too small in the image")
    return selected.mean(axis=0)


def detect_colorchecker(image_linear: np.ndarray) -> ChartDetection:
    """Find a ColorChecker 24 in a linear RGB image and average its patches in linear light.

    Uses ``cv2.mcc.CCheckerDetector`` (chart type MCC24) on an 8-bit sRGB-encoded copy, then averages the
    linear pixels inside the centre part of each detected patch (``CChecker.getColorCharts``, shrunk by
    :data:`PATCH_SHRINK` about each patch centre).

    Args:
        image_linear: ``(H, W, 3)`` float, scene-linear RGB.
    Returns:
        :class:`ChartDetection`.
    Raises:
        ChartNotFoundError: with advice when no chart is found.
    """
    import cv2

    image = np.asarray(image_linear)
    if image.ndim != 3 or image.shape[2] != 3 or not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"expected a float (H, W, 3) linear RGB image, got {image.dtype} {image.shape}")
    detector = cv2.mcc.CCheckerDetector.create()
    detector.setColorChartType(cv2.mcc.MCC24)
    if not detector.process(_detection_image_bgr8(image), 1):
        raise ChartNotFoundError(
            "no ColorChecker 24 found; make sure the whole chart is visible, in focus and at least "
            "~200 px wide in the chart image (re-shoot it closer, or crop the chart image file around it)"
        )
    checker = detector.getBestColorChecker()
    corners = np.asarray(checker.getColorCharts(), dtype=np.float64).reshape(-1, 4, 2)
    if corners.shape[0] != COLORCHECKER_PATCHES:
        raise ChartNotFoundError(f"detector returned {corners.shape[0]} patches, expected 24")
    centres = corners.mean(axis=1, keepdims=True)
    quads = centres + PATCH_SHRINK * (corners - centres)
    linear = image.astype(np.float64, copy=False)
    means = np.stack([_polygon_mean(linear, q) for q in quads])
    return ChartDetection(
        patch_means=means,
        patch_quads=quads,
        chart_quad=np.asarray(checker.getBox(), dtype=np.float64).reshape(4, 2),
        cost=float(checker.getCost()),
    )


def fit_chart_correction(
    image_linear: np.ndarray, method: str = "Cheung 2004", whitepoint: str = "D65"
) -> tuple[np.ndarray, ColourError]:
    """Detect the chart in ``image_linear (H, W, 3)`` and fit ``M (3, 3)`` with ``reference ≈ M @ measured``.

    Returns:
        ``(M, residual)``: the matrix and its :class:`ColourError` on the 24 patches. The matrix includes
        the exposure: it maps the capture to reflectance-scaled linear sRGB (white patch ≈ 0.88).
    """
    detection = detect_colorchecker(image_linear)
    reference = reference_colorchecker_linear(whitepoint)
    M = fit_ccm(detection.patch_means, reference, method=method)
    return M, ccm_error(detection.patch_means, reference, M)
