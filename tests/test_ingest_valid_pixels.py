"""Crops that reach past the source image's edge: every row says which of its pixels came from the source,
and no mask covers the zero padding (a camera framing the head off-image, as real rigs do)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.custom_capture import SIZE, ingest, make_capture

from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.validate import validate_path
from relightanyone.ingest.steps import undistort_crop_resize, undistort_crop_resize_valid


def test_crops_past_the_image_edge_keep_masks_inside_the_valid_pixels(tmp_path):
    capture = make_capture(tmp_path / "capture", subjects=("s1",), frames=(0,))
    cameras_path = capture / "cameras.json"
    document = json.loads(cameras_path.read_text())
    width, height = SIZE
    # c0 sees the head at the left edge through its lens distortion (the remap path); c1, a pinhole,
    # at the top edge (the slicing path). Half the head is then outside their images.
    document["cameras"]["c0"]["K"][0][2] = 4.0
    document["cameras"]["c1"]["K"][1][2] = 6.0
    document["cameras"]["c1"]["dist"] = [0.0] * 5
    cameras_path.write_text(json.dumps(document))

    summary = ingest(capture, tmp_path / "out")
    assert (summary.rows, summary.quarantined) == (4, 0)
    dataset = NormalizedDataset(summary.path)
    for key in dataset.keys:
        row, image, mask = dataset.decoded(key)
        valid = row.valid_pixels()
        assert not np.any(mask[~valid]), key
        # Exact: pure padding (black in every channel; the noise images never are) is never valid, and
        # every pixel the source fills alone is valid.
        black = ~image.any(axis=2)
        assert not np.any(black & valid), key
        if row.camera in ("c0", "c1"):
            x0, y0, x1, y1 = row.crop
            assert (x0 < 0) if row.camera == "c0" else (y0 < 0), row.crop
            assert black.any() and (~valid).sum() >= black.sum(), key
            side = x1 - x0
            inside = (min(x1, width) - max(x0, 0)) * (min(y1, height) - max(y0, 0)) / side**2
            assert abs(valid.mean() - inside) < 0.1, (key, valid.mean(), inside)
        else:
            assert valid.all(), key
    assert validate_path(summary.path) == []


@pytest.mark.parametrize(
    "box, out_size, first_valid_column",
    [
        # Downscaled by 3 (sliced, then area-averaged): output column k averages source columns
        # x0 + 3k .. x0 + 3k + 2, all inside from k = 5 (column 4 reaches source column -1).
        ((-13, 5, 47, 65), 20, 5),
        # Upscaled by 4 (bilinear at the output pixel centres, x = x0 + (k + 0.5) / 4 - 0.5): both taps
        # inside from x >= 0, k = 10 (column 9 samples x = -0.125, a quarter of it padding).
        ((-2, 10, 8, 20), 40, 10),
    ],
)
def test_valid_pixels_follow_the_half_pixel_rule(box, out_size, first_valid_column):
    K = np.array([[90.0, 0.0, 49.5], [0.0, 90.0, 39.5], [0.0, 0.0, 1.0]])
    image = np.full((80, 100, 3), 0.5, np.float32)
    out, _, valid = undistort_crop_resize_valid(image, K, None, box, out_size)
    assert not valid[:, :first_valid_column].any() and valid[:, first_valid_column:].all()
    np.testing.assert_allclose(out[valid], 0.5, rtol=1e-6)  # a valid pixel holds no padding
    assert (out[~valid] < 0.5).all()


@pytest.mark.parametrize("dist", [None, [0.05, -0.02, 0.001, 0.0, 0.0]], ids=["pinhole", "distorted"])
def test_valid_pixels_are_where_an_all_ones_source_stays_one(dist):
    # The definition, evaluated the slow way: the resampler run on an all-ones source (float32).
    K = np.array([[90.0, 0.0, 49.5], [0.0, 90.0, 39.5], [0.0, 0.0, 1.0]])
    ones = np.ones((80, 100), np.float32)
    rng = np.random.default_rng(3)
    for _ in range(12):
        side = int(rng.integers(8, 90))
        x0, y0 = int(rng.integers(-side + 2, 98)), int(rng.integers(-side + 2, 78))
        box = (x0, y0, x0 + side, y0 + side)
        out_size = int(rng.integers(6, 40))
        coverage, _ = undistort_crop_resize(ones, K, dist, box, out_size)
        _, _, valid = undistort_crop_resize_valid(ones, K, dist, box, out_size)
        expected = coverage >= 1.0 - 1e-5
        assert np.array_equal(valid, expected), (box, out_size, int((valid != expected).sum()))
