"""Inputs of the OLAT expansion: the two training runs (checked, loaded together, hashed) and the
provenance of the expanded dataset."""

from __future__ import annotations

from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.format.schema import Provenance
from relightanyone.hashing import sha256_file
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.run_files import CHECKPOINT_NAME, RUN_INFO_NAME, read_run_info
from relightanyone.pipelines.expand.task import cache_relightable_model


def stage2_olat_dataset(stage2: Path) -> Path:
    info = read_run_info(stage2, "stage2")
    try:
        return Path(info["dataset"]["path"])
    except (KeyError, TypeError) as error:
        raise InputError(
            f"{Path(stage2) / RUN_INFO_NAME}: field 'dataset.path' is missing ({error})"
        ) from None


def load_model_early(stage1: Path, stage2: Path) -> list[str]:
    """Load the two runs together now (clear errors before any work; the in-process task reuses the model)
    and return the stage-1 subjects ("<dataset>/<subject>") in identity-code order."""

    try:
        cache_relightable_model(Path(stage1).resolve(), Path(stage2).resolve())
        return list(load_checkpoint(Path(stage1) / CHECKPOINT_NAME)["subjects"])
    except (KeyError, TypeError, RuntimeError) as error:
        raise InputError(
            f"stage-1 run {stage1} and stage-2 run {stage2} do not load together ({error!r}); "
            "pass the stage-1 run the stage-2 run was trained on"
        ) from None


def checkpoint_sha256(run: Path, what: str) -> str:
    path = Path(run) / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the {what} run has no checkpoint; train it first")
    return sha256_file(path)


def dataset_provenance(source, settings, inputs: dict) -> Provenance:
    """The source dataset (its manifest hash, with its own provenance as parent) and both checkpoints."""
    own = source.manifest.info.provenance
    return Provenance(
        source_dataset=f"OLAT expansion of {source.name} by the two-stage model",
        licence=own.licence,
        tracker=own.tracker,
        template=own.template,
        parents=[
            Provenance(
                source_dataset=(
                    f"dataset {source.name} ({settings.source}) manifest sha256:"
                    f"{inputs['source_manifest_sha256']} config {inputs['source_config_fingerprint']}"
                ),
                licence=own.licence,
                tracker=own.tracker,
                template=own.template,
                parents=[own],
            ),
            Provenance(
                source_dataset=(
                    f"stage-1 checkpoint {settings.stage1 / CHECKPOINT_NAME} "
                    f"sha256:{inputs['stage1_checkpoint_sha256']}"
                ),
                licence=own.licence,
            ),
            Provenance(
                source_dataset=(
                    f"stage-2 checkpoint {settings.stage2 / CHECKPOINT_NAME} "
                    f"sha256:{inputs['stage2_checkpoint_sha256']}"
                ),
                licence=own.licence,
            ),
        ],
    )
