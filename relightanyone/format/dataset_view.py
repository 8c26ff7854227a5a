"""A view of a normalized dataset: the same rows under another folder, with side files of its own.

Steps that learn something *about* a dataset (the colour warm-up's 3×3 matrix) must not write into the
dataset they read: a pipeline treats that folder as another stage's finished output, and a dataset
shared between experiments should not change under them. Such a step writes a view instead: a folder of
relative symbolic links to the files the dataset format defines (the manifest, the files it lists, and
the quarantine log and side files the source holds) plus its own side files. Readers cannot tell a view
from the dataset; the source stays untouched.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.format.reader import load_manifest
from relightanyone.format.schema import MANIFEST_NAME, UNLISTED_FILE_NAMES


def dataset_file_names(dataset_dir: Path) -> list[str]:
    """The files of the dataset at ``dataset_dir`` (sorted): the manifest, every file it lists, and each of
    the format's unlisted files (quarantine log, side files) the folder holds.

    Raises ``FileNotFoundError`` naming the folder when a listed file is missing.
    """
    dataset_dir = Path(dataset_dir)
    listed = [MANIFEST_NAME, *(entry.file for entry in load_manifest(dataset_dir).listed_files())]
    missing = [name for name in listed if not (dataset_dir / name).is_file()]
    if missing:
        raise FileNotFoundError(f"{dataset_dir}: files listed in {MANIFEST_NAME} are missing: {missing}")
    return sorted([*listed, *(name for name in UNLISTED_FILE_NAMES if (dataset_dir / name).is_file())])


def link_dataset_view(source: Path, dest: Path, exclude: frozenset[str] = frozenset()) -> Path:
    """Make ``dest`` a view of the dataset folder ``source``; returns ``dest``.

    Each of the dataset's files (:func:`dataset_file_names`) except the names in ``exclude`` (e.g. side
    files the view replaces) becomes a relative link in ``dest``; anything else in ``source`` (a
    pipeline's records, say) is not part of the dataset. ``dest`` is replaced if it exists.
    """
    source, dest = Path(source), Path(dest)
    if not (source / MANIFEST_NAME).is_file():
        raise FileNotFoundError(f"{source}: not a normalized dataset (no {MANIFEST_NAME}); ingest it first")
    if dest.resolve() == source.resolve():
        raise InputError(f"{dest}: a view cannot replace the dataset it shows")
    names = [name for name in dataset_file_names(source) if name not in exclude]
    if dest.is_symlink() or dest.is_file():
        dest.unlink()
    elif dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for name in names:
        link = dest / name
        link.symlink_to(os.path.relpath((source / name).resolve(), dest.resolve()))
    return dest
