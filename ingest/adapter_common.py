"""What the adapters share: the plan an adapter returns, and paths relative to the dataset's root.

Adapters never import each other (each reads its own layout); code that several of them need lives here.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from relightanyone.ingest.records import AdapterOptions, DatasetPlan, SubjectPlan


def adapter_plan(
    name: str,
    kind: str,
    source_dataset: str,
    licence: str,
    version: str,
    src: Path,
    options: AdapterOptions,
    subjects: list[SubjectPlan],
    **details: Any,
) -> DatasetPlan:
    """The plan adapter ``name`` found under ``src`` in layout ``version``: the dataset is named
    ``options.dataset_name`` or ``name``; ``details`` are the plan's optional fields (refusals, found, ...)."""
    return DatasetPlan(
        dataset=options.dataset_name or name,
        kind=kind,
        layout=name,
        layout_version=version,
        source_root=str(src),
        source_dataset=source_dataset,
        licence=licence,
        subjects=subjects,
        **details,
    )


def root_relative(folder: Path, root: Path) -> Callable[[str], str]:
    """``part -> path`` of a file ``part`` of ``folder`` relative to the dataset root ``root`` (POSIX), the
    form rows and refusals record; ``part`` itself when ``folder`` is the root."""
    prefix = folder.relative_to(root).as_posix() if folder != root else ""
    return lambda part: f"{prefix}/{part}" if prefix else part
