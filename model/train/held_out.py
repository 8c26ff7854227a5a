"""Held-out-view PSNR and SSIM of a stage-1 model, per dataset.

Every training subject keeps a few cameras out of training (:class:`relightanyone.model.train.data.Stage1Data`).
They are rendered at the stored image size with the subject's own lighting code and compared with
the ground truth by the toolkit's metrics (:mod:`relightanyone.model.metrics`): per-view PSNR and SSIM
over the interior of the row's mask (its one-pixel edge ring mixes head and background, as the evaluation's
tables exclude it too), averaged over the views of a dataset; PSNR over the whole row mask is kept beside
it. Under torchrun the processes share the views
(:func:`relightanyone.model.train.distributed.shard`) and gather the scores.
"""

from __future__ import annotations

import numpy as np
import torch

from relightanyone.model.metrics import interior_mask, masked_psnr, masked_ssim
from relightanyone.model.networks.render import render_gaussians
from relightanyone.model.networks.stage1 import Stage1Model
from relightanyone.model.train.data import Stage1Data, ViewRef
from relightanyone.model.train.distributed import ProcessGroup, gather_items, shard
from relightanyone.model.train.sampling import evenly_spread


@torch.no_grad()
def render_view(
    model: Stage1Model,
    data: Stage1Data,
    view: ViewRef,
    use_lighting: bool = True,
    dataset_colour: bool = False,
) -> dict[str, torch.Tensor]:
    """Render one stored view at full size. Returns render, image (1, 3, H, W) and mask (1, 1, H, W).

    ``dataset_colour`` maps the render through the dataset's learned warm-up matrix (uncalibrated only).
    """
    item = data.load_view(view)
    _, height, width = item["image"].shape
    device = model.identity_codes.device
    subject = torch.tensor([view.subject_index], device=device)
    dataset = torch.tensor([view.dataset_index], device=device)
    _, gaussians = model(subject, dataset, use_lighting=use_lighting)
    K = item["K"].to(device=device, dtype=torch.float32)[None]
    w2c = item["w2c"].to(device=device, dtype=torch.float32)[None]
    render, _ = render_gaussians(gaussians, K, w2c, width, height)
    if dataset_colour:
        render = model.dataset_colour(render, dataset)
    return {"render": render.cpu(), "image": item["image"][None], "mask": item["mask"][None]}


def held_out_selection(
    data: Stage1Data, max_views_per_dataset: int | None = None
) -> list[tuple[int, ViewRef]]:
    """(dataset index, view) of every held-out view scored, dataset by dataset; with
    ``max_views_per_dataset`` an evenly spread subset of each dataset's views."""
    selection = []
    for index in range(len(data.names)):
        views = data.held_out_views[index]
        if max_views_per_dataset is not None:
            views = evenly_spread(views, max_views_per_dataset)
        selection += [(index, view) for view in views]
    return selection


def evaluate_held_out(
    model: Stage1Model,
    data: Stage1Data,
    use_lighting: bool = True,
    dataset_colour: bool = False,
    max_views_per_dataset: int | None = None,
    group: ProcessGroup | None = None,
) -> dict[str, dict[str, float]]:
    """Mean held-out PSNR (dB) and SSIM per dataset name over the mask's interior, and PSNR over the whole
    row mask: ``{name: {"psnr", "ssim", "psnr_row_mask", "views"}}``.

    ``max_views_per_dataset`` evaluates an evenly spread subset of the held-out views (for quick checks).
    Under torchrun every process of ``group`` must call this: each renders and scores its share of the
    views, the scores are gathered and averaged in view order, so every process returns the scores one
    process would have computed.
    """
    was_training = model.training
    model.eval()
    selection = held_out_selection(data, max_views_per_dataset)
    scores = []
    for position, (index, view) in shard(selection, group) if group else enumerate(selection):
        out = render_view(model, data, view, use_lighting, dataset_colour)
        interior = interior_mask(out["mask"])
        psnr = float(masked_psnr(out["render"], out["image"], interior)[0])
        ssim = float(masked_ssim(out["render"], out["image"], interior)[0])
        whole = float(masked_psnr(out["render"], out["image"], out["mask"])[0])
        scores.append((position, index, psnr, ssim, whole))
    if group:
        scores = gather_items(scores, group)
    scores.sort()
    model.train(was_training)
    results = {}
    for index, name in enumerate(data.names):
        mine = np.asarray([score[2:] for score in scores if score[1] == index], dtype=np.float64).reshape(
            -1, 3
        )
        means = mine.mean(axis=0) if len(mine) else np.full(3, np.nan)
        results[name] = {
            "psnr": float(means[0]),
            "ssim": float(means[1]),
            "psnr_row_mask": float(means[2]),
            "views": len(mine),
        }
    return results
