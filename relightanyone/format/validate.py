"""Checking a normalized dataset, reporting every problem with its file and row.

``validate_path(DIR)`` accepts one dataset folder or a root holding several and returns a list of
``Problem``; an empty list means the data is sound. Checks: manifest present and of the current format
version; at least one image row; every listed file present, of the listed size (truncation) and sha256
(any changed byte); no shard listed twice; no unlisted shard or leftover temporary file; shard schema; every row's values matching its
checksum (a changed shard is still read, so the corrupted rows are named; past a row that cannot be
decompressed, the rows are read at their offsets in the index); keys unique across shards and
equal to the index; names safe as file names; sane ``K`` and ``w2c``; images and masks decodable at the
declared size, and no mask pixel outside the row's valid pixels (on the zero padding past the source
image's edge); meshes, lights and quarantine readable, and the quarantine holding as many entries as the
manifest's ``quarantined``.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from relightanyone.format.arrow_io import read_batch_at, read_table_file
from relightanyone.format.codecs import CodecError, decode_image, decode_mask, decode_valid
from relightanyone.format.reader import IncompleteDatasetError, load_manifest
from relightanyone.format.schema import (
    CHECKSUM_COLUMN,
    FORMAT_VERSION,
    IMAGE_SCHEMA,
    INDEX_NAME,
    LIGHT_SCHEMA,
    MANIFEST_NAME,
    MESH_SCHEMA,
    QUARANTINE_NAME,
    FileEntry,
    QuarantineEntry,
    SchemaError,
    camera_problems,
    name_problem,
    row_checksum,
    row_label,
)
from relightanyone.format.shards import PARTS_DIR, dataset_dirs
from relightanyone.hashing import sha256_file
from relightanyone.progress import progress_bar


@dataclass(frozen=True)
class Problem:
    """One finding: the file, the row (or ``None`` for the whole file) and what is wrong."""

    file: str
    row: int | None
    message: str

    def __str__(self) -> str:
        where = self.file if self.row is None else f"{self.file} row {self.row}"
        return f"{where}: {self.message}"


def _check_listed_file(dataset_dir: Path, entry: FileEntry) -> list[Problem]:
    path = dataset_dir / entry.file
    if not path.exists():
        return [Problem(str(path), None, "listed in manifest.json but missing")]
    size = path.stat().st_size
    if size != entry.bytes:
        state = "truncated" if size < entry.bytes else "longer than listed"
        return [Problem(str(path), None, f"{state}: {size} bytes, manifest.json says {entry.bytes}")]
    if sha256_file(path) != entry.sha256:
        return [
            Problem(str(path), None, "sha256 differs from manifest.json (the file was changed or corrupted)")
        ]
    return []


def _open_stream(
    path: Path, schema: pa.Schema, problems: list[Problem]
) -> pa.ipc.RecordBatchStreamReader | None:
    try:
        reader = pa.ipc.open_stream(pa.memory_map(str(path)))
    except (pa.ArrowException, OSError) as error:
        problems.append(Problem(str(path), None, f"not a readable Arrow IPC stream ({error})"))
        return None
    if not reader.schema.equals(schema, check_metadata=True):
        problems.append(
            Problem(
                str(path),
                None,
                f"schema differs from format version {FORMAT_VERSION} ({reader.schema.metadata})",
            )
        )
        return None
    return reader


def _name_problems(values: dict) -> list[str]:
    """The row's names that are not one safe file name: each becomes a path component on export."""
    problems = []
    for what in ("dataset", "subject", "camera", "pattern"):
        problem = name_problem(values[what])
        if problem is not None:
            problems.append(f"{what} name {values[what]!r} {problem}")
    return problems


def _check_image_row(path: Path, row_number: int, values: dict, decode: bool) -> list[Problem]:
    if row_checksum(values) != values[CHECKSUM_COLUMN.name]:
        message = "the row's values do not match its checksum (corrupted)"
        return [Problem(str(path), row_number, f"{row_label(values)}: {message}")]
    found = _name_problems(values)
    found += camera_problems(values["K"], values["w2c"], values["width"], values["height"])
    problems = [Problem(str(path), row_number, f"{values['key']}: {p}") for p in found]
    if not decode:
        return problems
    size = (values["height"], values["width"])
    try:
        image = decode_image(values["image"], values["image_encoding"])
        if image.shape != (*size, 3):
            problems.append(
                Problem(str(path), row_number, f"{values['key']}: image is {image.shape}, declared {size}")
            )
        elif not np.all(np.isfinite(image)):
            problems.append(Problem(str(path), row_number, f"{values['key']}: image has non-finite pixels"))
    except CodecError as error:
        problems.append(Problem(str(path), row_number, f"{values['key']}: image does not decode ({error})"))
    try:
        mask = decode_mask(values["mask"])
        if mask.shape != size:
            problems.append(
                Problem(str(path), row_number, f"{values['key']}: mask is {mask.shape}, declared {size}")
            )
        else:
            outside = int(np.count_nonzero(mask[~decode_valid(values["valid"], *size)]))
            if outside:
                problems.append(
                    Problem(
                        str(path),
                        row_number,
                        f"{row_label(values)}: mask covers {outside} pixel(s) outside the source image "
                        "(clear bits of `valid`: zero padding past the image's edge)",
                    )
                )
    except CodecError as error:
        problems.append(Problem(str(path), row_number, f"{values['key']}: mask does not decode ({error})"))
    return problems


def _indexed_rows(index: pa.Table | None, shard_number: int) -> list[tuple[int, str]]:
    """(byte offset, key) of the index's rows in shard ``shard_number``, in stream order; empty without
    an index."""
    if index is None:
        return []
    shards = index.column("shard").to_pylist()
    offsets = index.column("batch_offset").to_pylist()
    keys = index.column("key").to_pylist()
    return sorted((o, k) for s, o, k in zip(shards, offsets, keys, strict=True) if s == shard_number)


def _key_values(key: str) -> dict:
    """The name fields of an image key ``<dataset>/<subject>/<frame:06d>/<camera>/<pattern>``."""
    dataset, subject, frame, camera, _ = (key.split("/") + [""] * 5)[:5]
    frame = int(frame) if frame.isdigit() else frame
    return {"key": key, "dataset": dataset, "subject": subject, "camera": camera, "frame": frame}


def _check_table(path: Path, schema: pa.Schema, problems: list[Problem]) -> pa.Table | None:
    reader = _open_stream(path, schema, problems)
    if reader is None:
        return None
    try:
        return reader.read_all()
    except (pa.ArrowException, OSError) as error:
        problems.append(Problem(str(path), None, f"cannot be read ({error})"))
        return None


def validate_dataset(dataset_dir: Path, decode: bool = True, progress: bool = False) -> list[Problem]:
    """All problems of one dataset folder."""
    dataset_dir = Path(dataset_dir)
    try:
        manifest = load_manifest(dataset_dir)
    except (IncompleteDatasetError, SchemaError) as error:
        return [Problem(str(dataset_dir / MANIFEST_NAME), None, str(error))]
    problems: list[Problem] = []
    if manifest.counts.get("images", 0) == 0:
        problems.append(
            Problem(
                str(dataset_dir / MANIFEST_NAME),
                None,
                f"the dataset holds no image row ({manifest.quarantined} items quarantined, see {QUARANTINE_NAME})",
            )
        )
    listed = Counter(entry.file for entry in manifest.shards)
    for name, times in sorted(listed.items()):
        if times > 1:
            problems.append(
                Problem(str(dataset_dir / MANIFEST_NAME), None, f"shard {name} is listed {times} times")
            )
    for path in sorted(dataset_dir.glob("images-*.arrow")):
        if path.name not in listed:
            problems.append(
                Problem(str(path), None, "shard is not listed in manifest.json, so it is not trusted")
            )
    for path in sorted([*dataset_dir.glob("*.tmp"), dataset_dir / PARTS_DIR]):
        if path.exists():
            problems.append(Problem(str(path), None, "leftover of an interrupted write"))

    side_files = (manifest.meshes, manifest.lights, manifest.quarantine)
    entries = [*manifest.shards, manifest.index, *(e for e in side_files if e)]
    intact: set[str] = set()
    for entry in {entry.file: entry for entry in reversed(entries)}.values():  # each file once
        file_problems = _check_listed_file(dataset_dir, entry)
        problems += file_problems
        if not file_problems:
            intact.add(entry.file)
    # A shard of the listed size whose hash differs is read anyway: the row checksums name the bad rows.
    readable = intact | {
        e.file
        for e in manifest.shards
        if (dataset_dir / e.file).is_file() and (dataset_dir / e.file).stat().st_size == e.bytes
    }

    seen: dict[str, str] = {}
    index_path = dataset_dir / INDEX_NAME
    index = read_table_file(index_path) if manifest.index.file in intact else None
    total = sum(entry.rows for entry in manifest.shards)
    bar = progress_bar(total=total, desc=f"validate {manifest.info.name}", unit="row", disable=not progress)

    def check(path: Path, row_number: int, values: dict) -> None:
        key = values["key"]
        if key in seen:
            problems.append(Problem(str(path), row_number, f"key {key!r} also in {seen[key]}"))
        seen[key] = f"{path.name} row {row_number}"
        problems.extend(_check_image_row(path, row_number, values, decode))
        bar.update()

    checked: set[str] = set()
    for shard_number, shard in enumerate(manifest.shards):
        entry, path = shard.file, dataset_dir / shard.file
        if entry in checked or entry not in readable:
            continue
        checked.add(entry)
        reader = _open_stream(path, IMAGE_SCHEMA, problems)
        if reader is None:
            continue
        row_number = 0
        try:
            for batch in reader:
                batch.validate(full=True)  # offsets inside their buffers before any value is read
                for values in batch.to_pylist():
                    check(path, row_number, values)
                    row_number += 1
        except (pa.ArrowException, OSError) as error:
            # The stream cannot be followed past a corrupted row; the index says which row it is and
            # where the next ones start, so every other row is still checked.
            located = _indexed_rows(index, shard_number)
            if row_number >= len(located):
                problems.append(Problem(str(path), row_number, f"cannot be read past this row ({error})"))
                continue
            source = pa.memory_map(str(path))
            for number in range(row_number, len(located)):
                offset, key = located[number]
                try:
                    batch = read_batch_at(source, offset, IMAGE_SCHEMA)
                    batch.validate(full=True)
                    check(path, number, batch.to_pylist()[0])
                except (pa.ArrowException, OSError) as row_error:
                    label = row_label(_key_values(key))
                    problems.append(Problem(str(path), number, f"{label}: cannot be read ({row_error})"))
    bar.close()

    if index is not None:
        if sorted(index.column("key").to_pylist()) != sorted(seen) and not problems:
            problems.append(Problem(str(index_path), None, "keys differ from the keys in the shards"))
    for entry, schema in ((manifest.meshes, MESH_SCHEMA), (manifest.lights, LIGHT_SCHEMA)):
        if entry is None or entry.file not in intact:
            continue
        table = _check_table(dataset_dir / entry.file, schema, problems)
        if table is not None and schema is MESH_SCHEMA:
            for row_number, (count, flat) in enumerate(
                zip(
                    table.column("vertex_count").to_pylist(),
                    table.column("vertices").to_pylist(),
                    strict=True,
                )
            ):
                if len(flat) != 3 * count or not np.all(np.isfinite(flat)):
                    problems.append(
                        Problem(
                            str(dataset_dir / entry.file),
                            row_number,
                            f"vertices must be 3 x vertex_count ({count}) finite values",
                        )
                    )
    problems += _check_quarantine(dataset_dir / QUARANTINE_NAME, manifest.quarantined)
    return problems


def _check_quarantine(path: Path, listed: int) -> list[Problem]:
    """Every line of ``quarantine.jsonl`` an entry, and as many entries as the manifest's ``quarantined``."""
    lines = path.read_text("utf-8").splitlines() if path.exists() else []
    problems = []
    entries = 0
    for number, line in enumerate(lines, start=1):
        if line.strip():
            entries += 1
            try:
                QuarantineEntry(**json.loads(line))
            except (json.JSONDecodeError, TypeError) as error:
                problems.append(Problem(str(path), number, f"not a quarantine entry ({error})"))
    if entries != listed:
        state = "missing, but" if not path.exists() else f"{entries} entries,"
        problems.append(
            Problem(str(path), None, f"{state} manifest.json says {listed} items were quarantined")
        )
    return problems


def validate_path(path: Path, decode: bool = True, progress: bool = False) -> list[Problem]:
    """Problems of every dataset under ``path`` (a dataset folder or a root of several)."""
    path = Path(path)
    if not path.is_dir():
        return [Problem(str(path), None, "not a folder")]
    datasets = dataset_dirs(path)
    if not datasets:
        return [Problem(str(path), None, "holds no dataset (no manifest.json here or in sub-folders)")]
    problems = []
    for dataset_dir in datasets:
        problems += validate_dataset(dataset_dir, decode=decode, progress=progress)
    return problems
