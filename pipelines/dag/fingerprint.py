"""Content fingerprints of files and folders, with a cache that avoids rehashing unchanged files.

The fingerprint of a folder is the sha256 of its sorted ``relative path, size, sha256`` lines over every
file below it, except the runner's own files (``is_runner_file``: ``_stage.json``, ``_stage.log``, a live
log), at any depth, since a folder may hold the outputs of several stages. The fingerprint of a file is the same over the one line ``".", size,
sha256``. File names and contents count; modification times and permissions do not.

Hashing terabytes on every run would be unusable, so each file's sha256 is cached under its absolute
path together with its size and ``st_mtime_ns``; the cache is stored in the ``_stage.json`` of the stage
that hashed the file and reloaded on the next run. A file is hashed again only when its size or
modification time changed (the usual trade-off of build tools: an edit that keeps both, to the
nanosecond, goes unnoticed; ``--force`` re-runs a stage regardless).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from relightanyone.hashing import sha256_file
from relightanyone.pipelines.dag.record import STAGE_LOG_NAME, STAGE_RECORD_NAME

RUNNER_FILE_NAMES = frozenset({STAGE_RECORD_NAME, STAGE_LOG_NAME})

# (size, mtime_ns, sha256 hex) of one file
FileEntry = tuple[int, int, str]


class HashCache:
    """Absolute path -> ``(size, mtime_ns, sha256)``; a lookup hashes only files whose stat changed."""

    def __init__(self) -> None:
        self.entries: dict[str, FileEntry] = {}
        self.hashed_files = 0  # files actually read (cache misses); for messages and tests

    def add_listing(self, root: Path, files: dict[str, list | tuple]) -> None:
        """Remember a listing written by :func:`listing_to_json` for the folder (or file) ``root``."""
        for relative, (size, mtime_ns, sha) in files.items():
            path = root if relative == "." else root / relative
            self.entries[str(path)] = (int(size), int(mtime_ns), str(sha))

    def entry(self, path: Path) -> FileEntry:
        """``(size, mtime_ns, sha256)`` of ``path``, from the cache when its size and mtime are unchanged."""
        stat = os.stat(path)
        cached = self.entries.get(str(path))
        if cached is not None and cached[0] == stat.st_size and cached[1] == stat.st_mtime_ns:
            return cached
        entry = (stat.st_size, stat.st_mtime_ns, sha256_file(path))
        self.hashed_files += 1
        self.entries[str(path)] = entry
        return entry


@dataclass(frozen=True)
class Fingerprint:
    """The content digest of a file or folder and the per-file entries it was computed from."""

    digest: str
    files: dict[str, FileEntry]


def is_runner_file(name: str) -> bool:
    """The runner's record and log, a record being written (``_stage.json.<random>.tmp``) and the live
    log of a running stage beside its output (``.<output name>_stage.log``)."""
    return (
        name in RUNNER_FILE_NAMES
        or (name.startswith(f"{STAGE_RECORD_NAME}.") and name.endswith(".tmp"))
        or (name.startswith(".") and name.endswith(STAGE_LOG_NAME))
    )


def list_files(root: Path) -> list[str]:
    """Relative POSIX paths of the files below ``root`` (sorted), without the runner's own files."""
    out = []
    for folder, dirnames, filenames in os.walk(root):
        dirnames.sort()
        base = Path(folder).relative_to(root)
        out.extend((base / name).as_posix() for name in filenames if not is_runner_file(name))
    return sorted(out)


def digest_of_entries(files: dict[str, FileEntry]) -> str:
    """sha256 over the sorted ``relative path, size, sha256`` lines (modification times excluded)."""
    digest = hashlib.sha256()
    for relative in sorted(files):
        size, _, sha = files[relative]
        digest.update(f"{relative}\0{size}\0{sha}\n".encode())
    return digest.hexdigest()


def fingerprint_path(path: Path, cache: HashCache) -> Fingerprint | None:
    """Fingerprint of the file or folder at ``path``; ``None`` when it does not exist."""
    path = Path(path)
    if path.is_file():
        files = {".": cache.entry(path)}
    elif path.is_dir():
        files = {relative: cache.entry(path / relative) for relative in list_files(path)}
    else:
        return None
    return Fingerprint(digest_of_entries(files), files)


def listing_to_json(files: dict[str, FileEntry]) -> dict[str, list]:
    """JSON-friendly form of a listing: ``{relative path: [size, mtime_ns, sha256]}``."""
    return {relative: list(entry) for relative, entry in sorted(files.items())}


def compare_listings(recorded: dict[str, list | tuple], current: dict[str, FileEntry]) -> str:
    """A short human description of how ``current`` differs from ``recorded`` (empty when equal)."""
    missing = sorted(set(recorded) - set(current))
    added = sorted(set(current) - set(recorded))
    modified = sorted(
        r
        for r in set(recorded) & set(current)
        if (int(recorded[r][0]), str(recorded[r][2])) != (current[r][0], current[r][2])
    )
    parts = []
    for label, names in (("modified", modified), ("missing", missing), ("added", added)):
        if names:
            more = f" and {len(names) - 2} more" if len(names) > 2 else ""
            parts.append(f"{label}: {', '.join(names[:2])}{more}")
    return "; ".join(parts)
