"""Deterministic batch sampling for stage-1 and stage-2 training (the crop transform itself is
:func:`relightanyone.format.torch_dataset.random_crop`).

Every random choice of iteration ``t`` is drawn from a generator seeded with ``(seed, t, ...)``. The
sampler therefore has no hidden state: its position is the iteration number, so resumed runs draw
exactly the batches an uninterrupted run draws. Data-parallel processes draw the same *global* batch and
each takes its own slice, and the crop of global sample ``j`` uses its own generator, so two processes
with batch ``b`` see exactly the samples one process with batch ``2b`` sees.

Balancing follows the paper: pick a dataset uniformly, then one of its training views uniformly, so a
small dataset is seen as often as a large one.
"""

from __future__ import annotations

import numpy as np

from relightanyone.errors import InputError

BATCH_STREAM = 0
CROP_STREAM = 1
BACKGROUND_STREAM = 3  # 2 is the stage-2 trainer's pattern stream


def iteration_generator(seed: int, iteration: int, stream: int, index: int = 0) -> np.random.Generator:
    """The generator of one use (``stream``) at one iteration, for item ``index`` (e.g. a global sample)."""
    return np.random.default_rng([int(seed), int(iteration), int(stream), int(index)])


def background_colours(seed: int, iteration: int, first_sample: int, count: int) -> np.ndarray:
    """(count, 3) float32 uniform random RGB backgrounds of global samples ``first_sample ..`` at ``iteration``.

    Drawn per sample from its own generator, so a resumed or multi-process run draws the same colours.
    """
    return np.stack(
        [
            iteration_generator(seed, iteration, BACKGROUND_STREAM, first_sample + i).random(3)
            for i in range(count)
        ]
    ).astype(np.float32)


def balanced_batch(
    views_per_dataset: list[int], batch_size: int, seed: int, iteration: int
) -> list[tuple[int, int]]:
    """``batch_size`` pairs (dataset index, view index within that dataset): the global batch of one iteration.

    Datasets are drawn uniformly (with replacement), then a view uniformly within the dataset.
    """
    if not views_per_dataset or min(views_per_dataset) <= 0:
        raise InputError(f"every dataset needs at least one training view, got counts {views_per_dataset}")
    rng = iteration_generator(seed, iteration, BATCH_STREAM)
    datasets = rng.integers(0, len(views_per_dataset), size=batch_size)
    return [(int(d), int(rng.integers(0, views_per_dataset[d]))) for d in datasets]


def evenly_spread(items: list, count: int) -> list:
    """Up to ``count`` of ``items`` spread evenly over their order (all of them when there are no more)."""
    if len(items) <= count:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


# At least this share of each subject's cameras trains, whatever the preset asks to hold out: a preset
# sized for a 40-camera light stage must not leave an 8-camera rig's subject with one training view.
MIN_TRAINING_CAMERA_SHARE = 0.75


def held_out_cameras(cameras: list[str], count: int, rotation: int = 0) -> set[str]:
    """``count`` cameras spread evenly over the sorted camera names, capped so that at least
    :data:`MIN_TRAINING_CAMERA_SHARE` of them train (none held out below four cameras).

    ``rotation`` (the subject's place in its dataset) turns the pattern by that many cameras, so that the
    subjects of one rig hold out different cameras and every camera trains on some subject: a camera's own
    colour response can then be learned, and held-out views are still never seen for their subject.
    """
    ordered = sorted(set(cameras))
    count = min(count, int(len(ordered) * (1 - MIN_TRAINING_CAMERA_SHARE) + 1e-9))
    if count <= 0:
        return set()
    step = len(ordered) / count
    return {ordered[(int(i * step + step / 2) + rotation) % len(ordered)] for i in range(count)}
