"""The files of a training run folder; stage 1, stage 2 and the single-stage baseline write the same set.

``checkpoint.pt`` (written by :mod:`relightanyone.model.train.checkpoint`), ``run.json`` (what the run
trains on and how, written when it starts; its ``trained_views`` lists every subject and camera whose rows
reached training, which the evaluation checks its held-out subjects against), ``metrics.json`` (written when it ends) and the template mesh
it trains with, copied from its dataset under the dataset's name for it
(:data:`relightanyone.format.schema.TEMPLATE_NAME`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from relightanyone.errors import InputError

CHECKPOINT_NAME = "checkpoint.pt"
RUN_INFO_NAME = "run.json"
METRICS_NAME = "metrics.json"


TRAINED_VIEWS_KEY = "trained_views"  # run.json: {"<dataset>/<subject>": [cameras whose rows trained]}


def read_run_info(run: Path | str, stage: str | None = None) -> dict:
    """The ``run.json`` of the training run folder ``run``; with ``stage`` ("stage1", "stage2",
    "single-stage", ...), checked to record that stage. InputError naming the file when it is missing,
    not a JSON object, or of another stage."""
    path = Path(run) / RUN_INFO_NAME
    command = f"relightanyone train {stage}" if stage in ("stage1", "stage2") else "relightanyone train"
    if not path.is_file():
        raise InputError(
            f"{path}: not a training run folder (no {RUN_INFO_NAME}); train one with `{command}`"
        )
    try:
        info = json.loads(path.read_text())
    except ValueError as error:  # UnicodeDecodeError too
        raise InputError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(info, dict):
        raise InputError(f"{path}: not a JSON object; the run folder is damaged, train it again")
    if stage is not None and info.get("stage") != stage:
        raise InputError(
            f"{path}: field 'stage' is {info.get('stage')!r}, expected {stage!r}; pass a {stage} run here"
        )
    return info


def trained_views(views: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """``(<dataset>/<subject>, camera)`` pairs of the rows a run trains on -> {subject key: sorted cameras}."""
    cameras: dict[str, set[str]] = {}
    for subject, camera in views:
        cameras.setdefault(subject, set()).add(camera)
    return {subject: sorted(names) for subject, names in sorted(cameras.items())}
