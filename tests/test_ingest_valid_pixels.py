"""Crops that reach past the source image's edge: every row says which of its pixels came from the source,
and no mask covers the zero padding (a camera framing the head off-image, as real rigs do)."""

from __future__ import annotations

import json

import numpy as np
from helpers.custom_capture import SIZE, ingest, make_capture

from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.validate import validate_path


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
