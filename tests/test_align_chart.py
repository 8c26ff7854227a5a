"""ColorChecker detection and chart-fitted colour matrices on synthetically rendered charts."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relightanyone.align.chart import (
    ChartNotFoundError,
    detect_colorchecker,
    fit_chart_correction,
    reference_colorchecker_linear,
)

CAST = np.array([[0.9, 0.1, 0.0], [0.05, 0.8, 0.1], [0.0, 0.15, 1.1]])


def _render_chart(corners: np.ndarray, cast: np.ndarray, gain: float, rotate_180: bool = False) -> np.ndarray:
    """Linear (360, 480, 3) float32 image: the 24 reference patches on a dark frame, warped onto ``corners``
    over a grey background, seen through ``gain * cast`` with a little sensor noise."""
    patch, gap, rows, cols = 40, 8, 4, 6
    width, height = cols * patch + (cols + 1) * gap, rows * patch + (rows + 1) * gap
    chart = np.full((height, width, 3), 0.03, np.float32)
    for index, rgb in enumerate(reference_colorchecker_linear()):
        r, c = divmod(index, cols)
        y0, x0 = gap + r * (patch + gap), gap + c * (patch + gap)
        chart[y0 : y0 + patch, x0 : x0 + patch] = rgb
    if rotate_180:
        chart = chart[::-1, ::-1].copy()
    src = np.float32([[0, 0], [width, 0], [width, height], [0, height]])
    H = cv2.getPerspectiveTransform(src, np.float32(corners))
    warped = cv2.warpPerspective(chart, H, (480, 360), flags=cv2.INTER_LINEAR)
    coverage = cv2.warpPerspective(
        np.ones((height, width), np.float32), H, (480, 360), flags=cv2.INTER_LINEAR
    )
    # Cyan is outside the sRGB gamut (negative red), so blend with a coverage map, not a sentinel value.
    scene = (warped + (1.0 - coverage[..., None]) * 0.18).astype(np.float64)
    captured = gain * scene @ cast.T
    return (captured + np.random.default_rng(0).normal(0, 0.002, captured.shape)).astype(np.float32)


PERSPECTIVE = np.array([[100, 80], [380, 95], [370, 280], [110, 265]])


def test_reference_chart_is_linear_srgb_d65_reflectance():
    ref = reference_colorchecker_linear()
    assert ref.shape == (24, 3)
    # Neutral row: white ≈ 0.88 reflectance and nearly neutral; black ≈ 0.031.
    assert ref[18] == pytest.approx([0.879, 0.885, 0.835], abs=2e-3)
    assert ref[23] == pytest.approx([0.0314, 0.0315, 0.0323], abs=2e-4)
    assert ref[14, 0] > 3 * ref[14, 1]  # "red" patch
    assert not np.allclose(reference_colorchecker_linear("D50"), ref)
    with pytest.raises(ValueError, match="illuminant"):
        reference_colorchecker_linear("D99")


def test_detects_the_chart_and_recovers_the_cast():
    image = _render_chart(PERSPECTIVE, CAST, gain=0.5)
    detection = detect_colorchecker(image)
    expected = 0.5 * reference_colorchecker_linear() @ CAST.T
    assert detection.patch_means == pytest.approx(expected, abs=1e-3)
    assert detection.patch_quads.shape == (24, 4, 2)
    assert np.abs(detection.chart_quad - PERSPECTIVE).max() < 12
    M, residual = fit_chart_correction(image)
    assert M @ (0.5 * CAST) == pytest.approx(np.eye(3), abs=3e-3)
    assert residual.delta_e_mean < 0.3 and residual.rmse < 1e-3


def test_patch_order_follows_the_chart_not_the_image():
    # Same place, chart upside down: the patches must come back in chart order, not image order.
    image = _render_chart(PERSPECTIVE, np.eye(3), gain=1.0, rotate_180=True)
    detection = detect_colorchecker(image)
    assert detection.patch_means == pytest.approx(reference_colorchecker_linear(), abs=4e-3)


def test_no_chart_gives_advice():
    flat = np.full((200, 300, 3), 0.2, np.float32)
    with pytest.raises(ChartNotFoundError, match="visible"):
        detect_colorchecker(flat)
    with pytest.raises(ChartNotFoundError, match="black"):
        detect_colorchecker(np.zeros((50, 50, 3), np.float32))
    with pytest.raises(ValueError, match="float"):
        detect_colorchecker(np.zeros((50, 50, 3), np.uint8))
