"""Stage-1 losses, metrics, schedules, sampling and crops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relightanyone.format.torch_dataset import choose_crop, crop_array, random_crop
from relightanyone.model.networks.gaussians import MAX_SCALE, MIN_SCALE
from relightanyone.model.networks.presets import LossWeights, get_preset
from relightanyone.model.train.colour_warmup import colour_cast_error, correction_from_render_matrix
from relightanyone.model.train.losses import (
    composite_over_background,
    masked_l1,
    offset_l2,
    offset_weight,
    scale_bound_loss,
    ssim_loss,
    vertex_l2,
)
from relightanyone.model.train.sampling import (
    background_colours,
    balanced_batch,
    held_out_cameras,
    iteration_generator,
)
from relightanyone.render.camera import crop_intrinsics


def test_image_losses_only_count_masked_pixels():
    target = torch.rand(2, 3, 24, 24)
    mask = torch.zeros(2, 1, 24, 24)
    mask[:, :, 4:20, 4:20] = 1
    render = target.clone()
    render[:, :, :4] += 5.0  # wrong only outside the mask
    assert torch.allclose(masked_l1(render, target, mask), torch.zeros(2))
    assert torch.allclose(ssim_loss(render, target, mask), torch.zeros(2), atol=1e-6)
    render_inside = target.clone()
    render_inside[0, :, 8:12, 8:12] += 0.5
    l1 = masked_l1(render_inside, target, mask)
    assert l1[0] == pytest.approx(0.5 * 16 / 256, rel=1e-5) and l1[1] == 0
    loss = ssim_loss(render_inside, target, mask)
    assert loss[1] == pytest.approx(0.0, abs=1e-4) and loss[0] > 0.01
    with pytest.raises(ValueError, match="mask must be"):
        masked_l1(render, target, mask[:, :, :10])


def test_background_compositing_makes_coverage_count():
    """Over a background, a faint head no longer matches an opaque one, and spill outside the mask costs."""
    target = torch.full((1, 3, 8, 8), 0.4)
    mask = torch.zeros(1, 1, 8, 8)
    mask[..., 2:6, 2:6] = 1
    background = torch.tensor([[0.9, 0.1, 0.5]])
    # Opaque and exactly covering the mask: identical over any background.
    render_bg, target_bg = composite_over_background(target * mask, mask, target, mask, background)
    assert torch.allclose(render_bg, target_bg)
    assert torch.allclose(target_bg[0, :, 0, 0], background[0])  # outside: the background
    assert torch.allclose(target_bg[0, :, 3, 3], torch.full((3,), 0.4))  # inside: the image
    # A fog at a quarter coverage with 4x the colour matches inside the mask on black ...
    fog_alpha = 0.25 * mask
    fog = 1.6 * fog_alpha.expand(1, 3, 8, 8)
    assert torch.allclose(masked_l1(fog, target, mask), torch.zeros(1))
    # ... but not over a background: three quarters of it shows through.
    fog_bg, target_bg = composite_over_background(fog, fog_alpha, target, mask, background)
    assert torch.allclose(masked_l1(fog_bg, target_bg, mask), 0.75 * background.mean())
    # Spill: an opaque render wider than the mask.
    spill_bg, target_bg = composite_over_background(target, torch.ones_like(mask), target, mask, background)
    assert torch.allclose(masked_l1(spill_bg, target_bg, mask), torch.zeros(1))
    assert torch.allclose(masked_l1(spill_bg, target_bg, 1 - mask), (background - 0.4).abs().mean())


def test_background_colours_are_per_sample_and_reproducible():
    first = background_colours(0, 7, 0, 4)
    assert first.shape == (4, 3) and first.dtype == np.float32
    assert ((first >= 0) & (first < 1)).all()
    assert np.array_equal(first, background_colours(0, 7, 0, 4))  # a resumed run draws the same
    assert np.array_equal(first[2:], background_colours(0, 7, 2, 2))  # process 2 of a split batch too
    assert not np.array_equal(first, background_colours(0, 8, 0, 4))


def test_geometry_and_regularisers():
    tracked = torch.zeros(2, 5, 3)
    decoded = tracked.clone()
    decoded[..., 0] = 0.002  # 2 mm
    assert torch.allclose(vertex_l2(decoded, tracked), torch.full((2,), 4.0))
    assert torch.allclose(vertex_l2(decoded, tracked, torch.tensor([1.0, 0.0])), torch.tensor([4.0, 0.0]))
    inside = torch.full((1, 4, 3), 1.0)
    assert scale_bound_loss(inside).item() == 0
    small = torch.full((1, 4, 3), MIN_SCALE / 2)
    assert scale_bound_loss(small).item() == pytest.approx(2 / MIN_SCALE)
    large = torch.full((1, 4, 3), MAX_SCALE + 3)
    assert scale_bound_loss(large).item() == pytest.approx(9.0)
    assert offset_l2(torch.ones(1, 4, 3)).item() == pytest.approx(3.0)


def test_offset_weight_anneals_log_linearly_from_one_to_a_thousandth():
    weights = LossWeights()
    assert offset_weight(0, weights, 100) == pytest.approx(1.0)
    assert offset_weight(50, weights, 100) == pytest.approx(math.sqrt(1e-3))
    assert offset_weight(100, weights, 100) == pytest.approx(1e-3)
    assert offset_weight(10_000, weights, 100) == pytest.approx(1e-3)
    paper = get_preset("paper")
    assert paper.offset_anneal_iterations < paper.iterations


def test_balanced_batches_sample_datasets_uniformly_and_deterministically():
    counts = [1000, 10, 3]
    picks = [d for t in range(300) for d, _ in balanced_batch(counts, 4, seed=7, iteration=t)]
    share = np.bincount(picks, minlength=3) / len(picks)
    assert np.all(np.abs(share - 1 / 3) < 0.05)
    assert all(v < counts[d] for t in range(50) for d, v in balanced_batch(counts, 4, 7, t))
    assert balanced_batch(counts, 4, 7, 12) == balanced_batch(counts, 4, 7, 12)
    assert balanced_batch(counts, 4, 7, 12) != balanced_batch(counts, 4, 7, 13)
    with pytest.raises(ValueError, match="at least one training view"):
        balanced_batch([5, 0], 2, 0, 0)


def test_crops_keep_projection_consistent_and_pad_small_images():
    mask = np.zeros((40, 60), np.float32)
    mask[10:30, 30:50] = 1
    box = choose_crop(mask, 16, iteration_generator(0, 3, 1))
    assert 0 <= box.x0 <= 60 - 16 and 0 <= box.y0 <= 40 - 16
    K = np.array([[50.0, 0, 29.5], [0, 50.0, 19.5], [0, 0, 1]])
    point = np.array([0.1, -0.05, 1.0])
    u, v, _ = K @ point
    uc, vc, _ = crop_intrinsics(K, box.x0, box.y0) @ point
    assert (uc, vc) == pytest.approx((u - box.x0, v - box.y0))
    image = np.arange(2 * 40 * 60, dtype=np.float32).reshape(2, 40, 60)
    cropped = crop_array(image, box)
    assert np.array_equal(cropped, image[:, box.y0 : box.y0 + 16, box.x0 : box.x0 + 16])
    padded_box = choose_crop(np.ones((8, 8)), 12, iteration_generator(0, 0, 1))
    padded = crop_array(np.ones((1, 8, 8), np.float32), padded_box)
    assert padded.shape == (1, 12, 12) and padded.sum() == 64
    # A dataset item is cropped by the same draw: image, mask and the float64 K together.
    item = {
        "image": torch.from_numpy(image[:1].repeat(3, 0)),
        "mask": torch.from_numpy(mask[None]),
        "K": torch.from_numpy(K),
        "key": "k",
    }
    cropped_item = random_crop(item, 16, iteration_generator(0, 3, 1))
    assert cropped_item["key"] == "k" and cropped_item["K"].dtype == torch.float64
    assert np.array_equal(cropped_item["image"].numpy(), crop_array(item["image"].numpy(), box))
    assert np.array_equal(cropped_item["mask"].numpy(), crop_array(mask[None], box))
    assert np.array_equal(cropped_item["K"].numpy(), crop_intrinsics(K, box.x0, box.y0))


def test_held_out_cameras_are_spread_and_never_all():
    cameras = [f"cam{i:02d}" for i in range(8)]
    aside = held_out_cameras(cameras, 2)
    assert len(aside) == 2 and aside <= set(cameras)
    assert held_out_cameras(["a"], 3) == set()
    assert held_out_cameras(["a", "b", "c"], 5) == set()
    # Subjects of one rig hold out different cameras: over eight subjects every camera trains and every
    # camera is held out twice.
    patterns = [held_out_cameras(cameras, 2, rotation) for rotation in range(8)]
    assert len(set(map(frozenset, patterns))) == 4
    assert all(sum(c in p for p in patterns) == 2 for c in cameras)


@pytest.mark.parametrize("cameras", [4, 8, 12, 16, 40, 80])
def test_at_least_three_quarters_of_a_subjects_cameras_train(cameras):
    """The paper preset holds out 8 cameras per subject; an 8-camera rig still trains from 6 of them."""
    names = [f"cam{i:02d}" for i in range(cameras)]
    for requested in (1, 2, 4, 8, 100):
        aside = held_out_cameras(names, requested)
        assert cameras - len(aside) >= 0.75 * cameras
        assert len(aside) == min(requested, cameras // 4)


def test_colour_cast_error_is_zero_for_the_true_cast_and_gain_free():
    cast = np.array([[1.1, 0.05, 0.0], [0.0, 0.95, 0.02], [0.03, 0.0, 0.8]])
    exact = colour_cast_error(cast, [cast, cast])
    assert exact["relative_error"] == pytest.approx(0, abs=1e-12)
    assert exact["identity_baseline_relative_error"] > 0.1
    scaled = colour_cast_error(2 * cast, [cast])
    assert scaled["relative_error_after_gain"] == pytest.approx(0, abs=1e-12)
    assert scaled["residual_cast_max_offdiagonal_or_ratio"] == pytest.approx(0, abs=1e-12)
    assert np.allclose(correction_from_render_matrix(cast) @ cast, np.eye(3))
    with pytest.raises(ValueError, match="singular"):
        correction_from_render_matrix(np.zeros((3, 3)))
