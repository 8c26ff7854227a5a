"""Image metrics of the toolkit: masked PSNR, RMSE and SSIM, one value per image.

Every metric compares linear RGB images clipped to [0, 1] (peak 1) inside a mask: the pixels of the subject
in the ground truth. Images are ``(B, 3, H, W)``, masks ``(B, 1, H, W)`` in [0, 1]; each metric returns
``(B,)``. Stage 1's held-out views and the evaluation's tables are scored by these functions. Training
objectives are in :mod:`relightanyone.model.train.losses`.
"""

from __future__ import annotations

import torch
from kornia.metrics import ssim as kornia_ssim

SSIM_WINDOW = 11  # Gaussian window side of every SSIM, metric and training term
MIN_MSE = 1e-12  # PSNR of identical images stays finite (120 dB)


def check_metric_inputs(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> None:
    """Raise ValueError unless prediction and target are (B, 3, H, W) and mask is (B, 1, H, W)."""
    if prediction.shape != target.shape or prediction.ndim != 4 or prediction.shape[1] != 3:
        raise ValueError(
            f"prediction and target must both be (B, 3, H, W); got {tuple(prediction.shape)} and "
            f"{tuple(target.shape)}"
        )
    if mask.shape != (prediction.shape[0], 1, *prediction.shape[2:]):
        raise ValueError(
            f"mask must be (B, 1, H, W) = {(prediction.shape[0], 1, *prediction.shape[2:])}, "
            f"got {tuple(mask.shape)}"
        )


def interior_mask(mask: torch.Tensor) -> torch.Tensor:
    """The pixels whose 3×3 neighbourhood lies wholly inside the binary mask (mask > 0.5): (B, 1, H, W) in,
    (B, 1, H, W) float out.

    A silhouette's edge pixels mix the subject with the background (anti-aliasing, matting), and against a
    bright studio wall one such ring outweighs the whole face; metrics that score the subject read its
    interior. Past the image border counts as inside (as OpenCV's erosion does): a crop's edge is not the
    subject's.
    """
    outside = (mask <= 0.5).to(torch.float32)
    grown = torch.nn.functional.max_pool2d(outside, kernel_size=3, stride=1, padding=1)
    return (1.0 - grown).to(mask.dtype)


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the masked pixels and channels of each image -> (B,)."""
    check_metric_inputs(prediction, target, mask)
    error = (prediction.clamp(0, 1) - target.clamp(0, 1)).pow(2) * mask
    weight = (mask.sum(dim=(1, 2, 3)) * prediction.shape[1]).clamp(min=1.0)
    return error.sum(dim=(1, 2, 3)) / weight


def masked_psnr(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """PSNR in dB with peak 1 over the masked pixels -> (B,), at most 120 dB (``MIN_MSE``)."""
    return 10.0 * torch.log10(1.0 / masked_mse(prediction, target, mask).clamp(min=MIN_MSE))


def masked_rmse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Root mean squared error over the masked pixels -> (B,)."""
    return masked_mse(prediction, target, mask).sqrt()


def masked_ssim(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of kornia's SSIM map (11×11 Gaussian window) over the pixels with mask > 0.5 -> (B,).

    Both images are multiplied by that binary mask first, so the background cannot raise the score.
    """
    check_metric_inputs(prediction, target, mask)
    binary = (mask > 0.5).to(prediction.dtype)
    ssim_map = kornia_ssim(
        prediction.clamp(0, 1) * binary, target.clamp(0, 1) * binary, SSIM_WINDOW, max_val=1.0
    )
    return (ssim_map.mean(dim=1, keepdim=True) * binary).sum(dim=(1, 2, 3)) / binary.sum(dim=(1, 2, 3)).clamp(
        min=1.0
    )
