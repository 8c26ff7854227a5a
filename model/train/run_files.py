"""The files of a training run folder; stage 1, stage 2 and the single-stage baseline write the same set.

``checkpoint.pt`` (written by :mod:`relightanyone.model.train.checkpoint`), ``run.json`` (what the run
trains on and how, written when it starts; its ``trained_views`` lists every subject and camera whose rows
reached training, which the evaluation checks its held-out subjects against), ``metrics.json`` (written when it ends) and the template mesh
it trains with, copied from its dataset under the dataset's name for it
(:data:`relightanyone.format.schema.TEMPLATE_NAME`).
"""

from __future__ import annotations

from collections.abc import Iterable

CHECKPOINT_NAME = "checkpoint.pt"
RUN_INFO_NAME = "run.json"
METRICS_NAME = "metrics.json"
TRAINED_VIEWS_KEY = "trained_views"  # run.json: {"<dataset>/<subject>": [cameras whose rows trained]}


def trained_views(views: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """``(<dataset>/<subject>, camera)`` pairs of the rows a run trains on -> {subject key: sorted cameras}."""
    cameras: dict[str, set[str]] = {}
    for subject, camera in views:
        cameras.setdefault(subject, set()).add(camera)
    return {subject: sorted(names) for subject, names in sorted(cameras.items())}
