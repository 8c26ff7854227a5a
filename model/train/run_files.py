"""The files of a training run folder; stage 1, stage 2 and the single-stage baseline write the same set.

``checkpoint.pt`` (written by :mod:`relightanyone.model.train.checkpoint`), ``run.json`` (what the run
trains on and how, written when it starts), ``metrics.json`` (written when it ends) and the template mesh
it trains with, copied from its dataset under the dataset's name for it
(:data:`relightanyone.format.schema.TEMPLATE_NAME`).
"""

from __future__ import annotations

CHECKPOINT_NAME = "checkpoint.pt"
RUN_INFO_NAME = "run.json"
METRICS_NAME = "metrics.json"
