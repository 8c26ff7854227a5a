"""Image metrics of the evaluation: the toolkit's masked PSNR, RMSE and SSIM (:mod:`relightanyone.model.metrics`),
and LPIPS when it is available locally. Images are ``(B, 3, H, W)`` float32, masks ``(B, 1, H, W)`` in [0, 1].
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

from relightanyone.align.colour import linear_to_srgb
from relightanyone.model.metrics import check_metric_inputs, masked_psnr, masked_rmse, masked_ssim


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
        check_metric_inputs(prediction, target, mask)
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
        "ssim": masked_ssim(prediction, target, mask),
    }
    if lpips_metric is not None:
        scores["lpips"] = lpips_metric(prediction, target, mask)
    return scores
