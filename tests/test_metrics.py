"""The toolkit's image metrics: what masked PSNR, RMSE and SSIM mean on hand-made images."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relightanyone.model.metrics import interior_mask, masked_psnr, masked_rmse, masked_ssim


def test_psnr_is_per_image_over_the_mask_and_capped():
    target = torch.zeros(2, 3, 8, 8)
    prediction = target.clone()
    prediction[0] = 0.1  # image 0: error 0.1 everywhere -> 20 dB
    prediction[1, :, :, :4] = 0.01  # image 1: error 0.01 on the masked half -> 40 dB
    prediction[1, :, :, 4:] = 0.9  # ... and a large error outside its mask, which does not count
    mask = torch.ones(2, 1, 8, 8)
    mask[1, :, :, 4:] = 0
    psnr = masked_psnr(prediction, target, mask)
    assert psnr.shape == (2,)
    assert psnr.tolist() == pytest.approx([20.0, 40.0], abs=1e-4)  # per image, not pooled over the batch
    assert masked_rmse(prediction, target, mask).tolist() == pytest.approx([0.1, 0.01], rel=1e-5)
    # Identical images: 120 dB, not infinity; values are clipped to [0, 1] (peak 1) first.
    assert masked_psnr(target, target, mask).tolist() == pytest.approx([120.0, 120.0], abs=1e-3)
    assert float(masked_psnr(target + 3.0, target + 2.0, mask)[0]) == pytest.approx(120.0, abs=1e-3)


def test_ssim_uses_the_binary_mask_and_clipped_images():
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(1, 3, 24, 24, generator=generator) * 0.8
    mask = torch.zeros(1, 1, 24, 24)
    mask[..., 4:20, 4:20] = 1.0
    assert float(masked_ssim(target, target, mask)[0]) == pytest.approx(1.0, abs=1e-5)
    # Pixels with mask <= 0.5 do not count: changing them (or a faint soft mask there) leaves the score.
    outside = target.clone()
    outside[..., :2, :] = 0.0
    soft = mask.clone()
    soft[..., :2, :] = 0.4
    assert float(masked_ssim(outside, target, soft)[0]) == pytest.approx(1.0, abs=1e-5)
    # Values above 1 are clipped like the truth's: an over-bright copy of a saturated image scores 1.
    saturated = torch.ones(1, 3, 24, 24)
    assert float(masked_ssim(saturated * 1.5, saturated, mask)[0]) == pytest.approx(1.0, abs=1e-5)
    noisy = target + 0.2 * torch.randn(target.shape, generator=generator) * mask
    assert float(masked_ssim(noisy, target, mask)[0]) < 0.9
    with pytest.raises(ValueError, match="mask must be"):
        masked_ssim(target, target, mask[..., :10])


def test_interior_mask_drops_the_edge_ring_as_opencv_erosion_does():
    import cv2

    rng = np.random.default_rng(3)
    mask = np.zeros((40, 50), np.float32)
    cv2.circle(mask, (20, 18), 12, 1.0, -1)
    mask[30:, 35:] = 1.0  # touches the image border: past it counts as inside
    mask[5, 40] = 1.0  # a lone pixel has no interior
    soft = mask * rng.uniform(0.6, 1.0, mask.shape).astype(np.float32)  # any value > 0.5 is inside
    interior = interior_mask(torch.from_numpy(soft)[None, None])[0, 0].numpy()
    assert np.array_equal(interior, cv2.erode(mask, np.ones((3, 3), np.uint8)))
    assert interior[5, 40] == 0 and interior[39, 49] == 1 and interior.sum() < mask.sum()
