"""Image metrics of the evaluation: masked PSNR, RMSE and SSIM (kornia), and LPIPS when available locally.

Every metric compares linear RGB images clipped to [0, 1] (peak 1) inside a mask: the pixels of the
subject in the ground truth. Images are ``(B, 3, H, W)`` float32, masks ``(B, 1, H, W)`` in [0, 1].
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

from relightanyone.align.colour import linear_to_srgb

SSIM_WINDOW = 11
MIN_MSE = 1e-12  # PSNR of identical images stays finite (120 dB)


def _check(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> None:
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


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the masked pixels and channels of each image -> (B,)."""
    _check(prediction, target, mask)
    error = (prediction.clamp(0, 1) - target.clamp(0, 1)).pow(2) * mask
    weight = (mask.sum(dim=(1, 2, 3)) * prediction.shape[1]).clamp(min=1.0)
    return error.sum(dim=(1, 2, 3)) / weight


def masked_psnr(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """PSNR in dB with peak 1 over the masked pixels -> (B,)."""
    return 10.0 * torch.log10(1.0 / masked_mse(prediction, target, mask).clamp(min=MIN_MSE))


def masked_rmse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Root mean squared error over the masked pixels -> (B,)."""
    return masked_mse(prediction, target, mask).sqrt()


def masked_ssim_score(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of kornia's SSIM map (11×11 Gaussian window) over the masked pixels -> (B,).

    Both images are multiplied by the mask first, so the background cannot raise the score.
    """
    import kornia

    _check(prediction, target, mask)
    binary = (mask > 0.5).to(prediction.dtype)
    ssim_map = kornia.metrics.ssim(
        prediction.clamp(0, 1) * binary, target.clamp(0, 1) * binary, SSIM_WINDOW, max_val=1.0
    )
    return (ssim_map.mean(dim=1, keepdim=True) * binary).sum(dim=(1, 2, 3)) / binary.sum(dim=(1, 2, 3)).clamp(
        min=1.0
    )


def lpips_status() -> tuple[bool, str]:
    """(available, reason): LPIPS needs the ``lpips`` package and its AlexNet weights already on disk."""
    if importlib.util.find_spec("lpips") is None:
        return False, "LPIPS skipped: the `lpips` package is not installed"
    checkpoints = Path(torch.hub.get_dir()) / "checkpoints"
    if not any(checkpoints.glob("alexnet-*.pth")):
        return False, f"LPIPS skipped: no AlexNet weights under {checkpoints} (nothing is downloaded)"
    return True, "LPIPS (AlexNet, lpips package)"


class LpipsMetric:
    """Masked LPIPS on sRGB-encoded images; construct only when :func:`lpips_status` says available."""

    def __init__(self) -> None:
        import lpips

        self.network = lpips.LPIPS(net="alex", verbose=False).eval().requires_grad_(False)

    @torch.no_grad()
    def __call__(self, prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        _check(prediction, target, mask)
        binary = (mask > 0.5).to(prediction.dtype)
        # LPIPS was trained on display images in [-1, 1].
        to_input = lambda x: linear_to_srgb(x.clamp(0, 1) * binary) * 2 - 1  # noqa: E731
        return self.network(to_input(prediction), to_input(target)).reshape(-1)


def image_metrics(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    lpips_metric: LpipsMetric | None = None,
) -> dict[str, torch.Tensor]:
    """psnr, rmse, ssim (and lpips with a metric object) per image -> dict of (B,) tensors."""
    scores = {
        "psnr": masked_psnr(prediction, target, mask),
        "rmse": masked_rmse(prediction, target, mask),
        "ssim": masked_ssim_score(prediction, target, mask),
    }
    if lpips_metric is not None:
        scores["lpips"] = lpips_metric(prediction, target, mask)
    return scores
