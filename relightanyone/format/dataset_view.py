"""A view of a normalized dataset: the same rows under another folder, with side files of its own.

Steps that learn something *about* a dataset (the colour warm-up's 3×3 matrix) must not write into the
dataset they read: a pipeline treats that folder as another stage's finished output, and a dataset
shared between experiments should not change under them. Such a step writes a view instead: a folder of
relative symbolic links to every file of the source (manifest, shards, index, lights, meshes, template)
plus its own side files. Readers cannot tell a view from the dataset; the source stays untouched.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from relightanyone.errors import InputError

RUNNER_FILES = frozenset({"_stage.json", "_stage.log"})


def link_dataset_view(source: Path, dest: Path, exclude: frozenset[str] = frozenset()) -> Path:
    """Make ``dest`` a view of the dataset folder ``source``; returns ``dest``.

    Every file below ``source`` (except pipeline records and the names in ``exclude``, e.g. side files the
    view replaces) becomes a relative link in ``dest``; ``dest`` is replaced if it exists.
    """
    source, dest = Path(source), Path(dest)
    if not (source / "manifest.json").is_file():
        raise FileNotFoundError(f"{source}: not a normalized dataset (no manifest.json); ingest it first")
    if dest.resolve() == source.resolve():
        raise InputError(f"{dest}: a view cannot replace the dataset it shows")
    if dest.is_symlink() or dest.is_file():
        dest.unlink()
    elif dest.exists():
        shutil.rmtree(dest)
    for folder, dirnames, filenames in os.walk(source):
        dirnames.sort()
        relative = Path(folder).relative_to(source)
        (dest / relative).mkdir(parents=True, exist_ok=True)
        for name in sorted(filenames):
            if name in RUNNER_FILES or (relative == Path(".") and name in exclude):
                continue
            target = Path(folder) / name
            link = dest / relative / name
            link.symlink_to(os.path.relpath(target.resolve(), link.parent.resolve()))
    return dest
