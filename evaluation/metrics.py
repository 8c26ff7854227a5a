"""Image metrics of the evaluation: the toolkit's masked PSNR, RMSE and SSIM
(:mod:`relightanyone.model.metrics`) in linear RGB and in sRGB display space, and LPIPS when its backbone
is available offline. Images are ``(B, 3, H, W)`` float32 scene-linear, masks ``(B, 1, H, W)`` in [0, 1].

* **Linear**: both images clipped to [0, 1], compared inside the mask (PSNR peak 1, RMSE, SSIM with an
  11×11 Gaussian window over the binary mask ``mask > 0.5``).
* **sRGB** (suffix ``_srgb``): the same metrics on the display encoding of the clipped images
  (:func:`relightanyone.align.colour.linear_to_srgb`, the toolkit's one display conversion). Dark OLAT
  images differ by little in linear values; the display encoding weighs shadows as a viewer sees them.
* **Level-aligned PSNR** (``psnr_level_aligned``, linear): the PSNR after scaling the prediction by the one
  gain that fits it best to the target over the mask. A diagnostic, not a goal metric: under lighting the
  fit is not told, a light twice as bright and an albedo half as bright look the same, so part of a
  relighting error can be that level alone; this metric says how much.
* **LPIPS** (AlexNet, torchmetrics' implementation through torchvision) on the sRGB images with the
  background set to 0, computed only when torchmetrics and torchvision import and the AlexNet weights
  are already in the local torch cache; nothing is downloaded. Otherwise :func:`lpips_status` gives the
  reason, which the evaluation records.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

from relightanyone.align.colour import linear_to_srgb
from relightanyone.model.metrics import check_metric_inputs, masked_psnr, masked_rmse, masked_ssim

LINEAR_METRICS = ("psnr", "rmse", "ssim")
LEVEL_ALIGNED = "psnr_level_aligned"
SRGB_SUFFIX = "_srgb"
WEIGHTS_MISSING = "skipped: backbone weights not available offline"


def lpips_import_problem() -> str | None:
    """Why LPIPS cannot run here (a missing or broken torchmetrics / torchvision), or None."""
    for package in ("torchmetrics", "torchvision"):
        if importlib.util.find_spec(package) is None:
            return f"skipped: {package} is not installed"
    try:
        import torchvision  # noqa: F401  (deferred: a torchvision built for another torch fails here)
    except Exception as error:  # a binary mismatch raises anything from ImportError to RuntimeError
        return f"skipped: torchvision does not import beside this torch ({type(error).__name__})"
    return None


def alexnet_weights(checkpoints: Path) -> list[Path]:
    """The torchvision AlexNet weights already in a torch hub cache folder."""
    return sorted(Path(checkpoints).glob("alexnet-*.pth"))


def lpips_status(checkpoints: Path | None = None) -> tuple[bool, str]:
    """(available, what the evaluation records): LPIPS runs only with its backbone already on disk."""
    problem = lpips_import_problem()
    if problem is not None:
        return False, problem
    if not alexnet_weights(checkpoints or Path(torch.hub.get_dir()) / "checkpoints"):
        return False, WEIGHTS_MISSING
    return True, "LPIPS: AlexNet through torchvision, as torchmetrics computes it, on sRGB images"


class LpipsMetric:
    """Masked LPIPS on sRGB-encoded images; construct only when :func:`lpips_status` says available."""

    def __init__(self) -> None:
        # Deferred: torchmetrics is optional and only imported when its backbone is known to be cached.
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        self.network = LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True).eval()

    @torch.no_grad()
    def __call__(self, prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        check_metric_inputs(prediction, target, mask)
        binary = (mask > 0.5).to(prediction.dtype)
        display = lambda x: linear_to_srgb(x.clamp(0, 1)) * binary  # noqa: E731
        scores = []
        for p, t in zip(display(prediction), display(target), strict=True):
            scores.append(self.network(p[None].clamp(0, 1), t[None].clamp(0, 1)).reshape(()))
            self.network.reset()
        return torch.stack(scores)


def level_aligned_psnr(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """PSNR of ``g * prediction`` against ``target`` with the least-squares scalar ``g`` of each image over
    the mask (both clipped to [0, 1] first) -> (B,)."""
    check_metric_inputs(prediction, target, mask)
    p, t = prediction.clamp(0, 1), target.clamp(0, 1)
    weight = (mask > 0.5).to(p.dtype)
    gain = (p * t * weight).sum(dim=(1, 2, 3)) / (p * p * weight).sum(dim=(1, 2, 3)).clamp(min=1e-12)
    return masked_psnr((p * gain.view(-1, 1, 1, 1)).clamp(0, 1), t, weight)


def image_metrics(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    lpips_metric: LpipsMetric | None = None,
) -> dict[str, torch.Tensor]:
    """psnr, rmse, ssim in linear RGB, the same with suffix ``_srgb`` in display space, the level-aligned
    PSNR (and lpips with a metric object) per image -> dict of (B,) tensors."""
    linear = (prediction.clamp(0, 1), target.clamp(0, 1))
    display = tuple(linear_to_srgb(x) for x in linear)
    scores = {}
    for suffix, (p, t) in (("", linear), (SRGB_SUFFIX, display)):
        scores[f"psnr{suffix}"] = masked_psnr(p, t, mask)
        scores[f"rmse{suffix}"] = masked_rmse(p, t, mask)
        scores[f"ssim{suffix}"] = masked_ssim(p, t, mask)
    scores[LEVEL_ALIGNED] = level_aligned_psnr(prediction, target, mask)
    if lpips_metric is not None:
        scores["lpips"] = lpips_metric(prediction, target, mask)
    return scores
