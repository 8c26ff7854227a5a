"""Writing a normalized dataset: atomic, deterministic and resumable.

A dataset is produced in units of work ("tasks", typically one subject), possibly by several worker
processes, then committed once::

    writer = ShardWriter(root / "ava256", info, max_shard_bytes=256 << 20)
    writer.begin()                              # coordinator: the dataset is incomplete from now on
    writer.write_lights(lights)                 # OLAT datasets: list[LightRow]
    for task in tasks:                          # any executor; ShardWriter pickles to workers
        if writer.has_part(task):               # finished by an earlier, interrupted run
            continue
        with writer.part(task) as part:         # PartWriter
            part.add(image_row)                 # ImageRow (schema.build_image_row)
            part.add_mesh(mesh_row)             # MeshRow
            part.quarantine(entry)              # QuarantineEntry
        writer.publish(task)                    # coordinator, when a worker's task has returned
    manifest = writer.commit()                  # coordinator: shards, index, tables, manifest (last)

Files under ``<dataset>/``:

``_parts/<task>/``
    one finished task: ``images.arrow`` (+ ``offsets.json``), ``meshes.arrow``, ``quarantine.jsonl``.
    A task is written under ``_parts/<task>.tmp/`` and renamed (*published*) once its ``with`` block ends
    without error, so a killed worker leaves only a ``.tmp`` folder, which ``begin`` discards. Only the
    process that made the writer, the coordinator, publishes: in it the ``with`` block publishes the part;
    a part written elsewhere (a pool or Ray worker, which gets the writer pickled) stays in its ``.tmp``
    folder until the coordinator calls ``writer.publish(task)`` on the task's result. A worker that
    outlives a killed coordinator can therefore never make a part look finished.
``images-00000.arrow`` ...
    written by ``commit``: all rows of all parts sorted by key, one row per record batch, a new shard when
    the current one passes ``max_shard_bytes``. Same rows -> same bytes, whatever order or process the
    tasks ran in.
``index.arrow``, ``meshes.arrow``, ``lights.arrow``, ``quarantine.jsonl``
    the key index (key, metadata, shard, byte offset of the row's record batch), tables and refusals
    (one line per refused item; the manifest lists it with its hash, ``rows`` = entries).
``manifest.json``
    written last, atomically, with the sha256 and size of every file above. A dataset without it is
    incomplete and readers refuse it. ``commit`` removes ``_parts`` only after the manifest is durable.

``.lock``
    held by the coordinator from ``begin`` to ``commit`` (:mod:`relightanyone.locking`): one writer per
    dataset folder; removed by ``commit``, left unlocked by a killed run.

Resuming: run the same code again. ``begin`` removes the manifest and every ``*.tmp``, keeps the finished
parts when the config fingerprint is unchanged (drops them otherwise), and ``commit`` rewrites every shard
from the parts, so the output is byte-identical to an uninterrupted run. Shards left from an earlier run
are never trusted: they are rewritten or deleted.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import struct
from collections.abc import Iterable, Sequence
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

from relightanyone.format.arrow_io import (
    StreamFileWriter,
    atomic_write_bytes,
    fsync_dir,
    read_message_at,
    read_table_file,
    write_table_file,
)
from relightanyone.format.schema import (
    FORMAT_VERSION,
    IMAGE_SCHEMA,
    INDEX_COLUMNS,
    INDEX_NAME,
    INDEX_SCHEMA,
    LIGHT_SCHEMA,
    LIGHTS_NAME,
    MANIFEST_NAME,
    MESH_SCHEMA,
    MESHES_NAME,
    QUARANTINE_NAME,
    SHARD_PATTERN,
    DatasetInfo,
    FileEntry,
    ImageRow,
    LightRow,
    Manifest,
    MeshRow,
    QuarantineEntry,
    SchemaError,
)
from relightanyone.hashing import sha256_file
from relightanyone.locking import acquire_output_lock, release_output_lock
from relightanyone.progress import progress_bar

DEFAULT_MAX_SHARD_BYTES = 256 << 20
PARTS_DIR = "_parts"
# Files below PARTS_DIR: per task, its rows and their byte offsets; per dataset, the config stamp and the
# staged lights and quarantine.
_PART_IMAGES = "images.arrow"
_PART_OFFSETS = "offsets.json"
_CONFIG_STAMP = "_config.json"
_STAGED_LIGHTS = "_lights.arrow"
_STAGED_QUARANTINE = "_quarantine.jsonl"
_TASK_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_SHARD_NAME = re.compile(r"^images-(\d{5})\.arrow$")
# A Python object's default repr carries its memory address, which differs from run to run.
_OBJECT_ADDRESS = re.compile(r"\s+at 0x[0-9A-Fa-f]+(?=>)")


def deterministic_entry(entry: QuarantineEntry) -> QuarantineEntry:
    """``entry`` with the memory addresses of object reprs dropped from its reason (a decoder's error may
    name ``<_io.BytesIO object at 0x7f...>``), so the same input gives the same ``quarantine.jsonl``."""
    return dataclasses.replace(entry, reason=_OBJECT_ADDRESS.sub("", entry.reason))


class QuarantineLog:
    """An append-only ``quarantine.jsonl``: one JSON object per line, deduplicated by ``item``.

    Each append is a single ``O_APPEND`` write followed by fsync, so concurrent appenders do not interleave
    and a killed process can leave at most one torn last line, which reading ignores and the next append
    repairs.
    """

    def __init__(self, path: Path):
        self.path = Path(path)

    def entries(self) -> list[QuarantineEntry]:
        """Entries in file order, first one per item kept; a torn last line is skipped."""
        if not self.path.exists():
            return []
        seen: dict[str, QuarantineEntry] = {}
        lines = self.path.read_text(encoding="utf-8").split("\n")
        for number, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                entry = QuarantineEntry(**json.loads(line))
            except (json.JSONDecodeError, TypeError) as error:
                if number == len(lines):  # torn by a kill during the last append
                    continue
                raise SchemaError(f"{self.path}:{number}: not a quarantine entry ({error})") from None
            seen.setdefault(entry.item, entry)
        return list(seen.values())

    def append(self, entry: QuarantineEntry) -> bool:
        """Record ``entry`` unless its item is already recorded; returns whether it was written."""
        if any(e.item == entry.item for e in self.entries()):
            return False
        self._drop_torn_tail()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, (entry.to_json_line() + "\n").encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)
        return True

    def _drop_torn_tail(self) -> None:
        if not self.path.exists():
            return
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            with open(self.path, "rb+") as handle:
                handle.truncate(data.rfind(b"\n") + 1)


def _check_task_name(task: str) -> str:
    if not _TASK_NAME.match(task) or task.endswith(".tmp"):
        raise ValueError(f"task name {task!r} must match {_TASK_NAME.pattern} and not end with .tmp")
    return task


def _single_binary(value: bytes) -> pa.Array:
    """A one-element ``binary`` array over ``value`` without a copy (``pa.array`` appends the bytes
    through a builder: about 0.8 ms for a 128² float16 image, more than compressing it)."""
    offsets = pa.py_buffer(struct.pack("<ii", 0, len(value)))  # int32 offsets [0, len]
    return pa.Array.from_buffers(pa.binary(), 1, [None, offsets, pa.py_buffer(value)])


def _single_row_batch(schema: pa.Schema, values: dict) -> pa.RecordBatch:
    # Column by column: the same batch as ``from_pylist``, several times faster for one row.
    return pa.RecordBatch.from_arrays(
        [
            _single_binary(values[f.name])
            if f.type == pa.binary() and isinstance(values[f.name], bytes)
            else pa.array([values[f.name]], type=f.type)
            for f in schema
        ],
        schema=schema,
    )


def _publish_part(tmp_dir: Path, final_dir: Path) -> None:
    """Rename a finished task's folder to its final name, durably."""
    shutil.rmtree(final_dir, ignore_errors=True)
    os.replace(tmp_dir, final_dir)
    fsync_dir(final_dir.parent)


class PartWriter:
    """Rows of one task, written to ``_parts/<task>.tmp/`` and, when ``publish``, published atomically on
    ``close``."""

    def __init__(self, parts_dir: Path, task: str, compression_level: int, publish: bool = True):
        self.task = _check_task_name(task)
        self.publish = publish  # False in a worker: the coordinator publishes the finished folder
        self.final_dir = parts_dir / task
        self.tmp_dir = parts_dir / f"{task}.tmp"
        shutil.rmtree(self.tmp_dir, ignore_errors=True)
        self.tmp_dir.mkdir(parents=True)
        self._images = StreamFileWriter(self.tmp_dir / _PART_IMAGES, IMAGE_SCHEMA, compression_level)
        self._keys: list[str] = []
        self._index: list[list] = []  # INDEX_COLUMNS of every row, so the commit need not decode rows
        self._key_set: set[str] = set()
        self._meshes: dict[str, dict] = {}
        self._quarantine: dict[str, QuarantineEntry] = {}

    def add(self, row: ImageRow) -> None:
        """Add one image row (checked against the schema)."""
        if row.key in self._key_set:
            raise SchemaError(f"task {self.task!r}: image key {row.key!r} added twice")
        values = row.to_arrow_dict()
        self._images.write(_single_row_batch(IMAGE_SCHEMA, values))
        self._index.append([values[name] for name in INDEX_COLUMNS])
        self._keys.append(row.key)
        self._key_set.add(row.key)

    def withdraw(self, keys: set[str]) -> None:
        """Leave the rows of ``keys`` out of the part (their bytes stay in the part's file until the commit,
        which copies only the rows listed)."""
        kept = [i for i, key in enumerate(self._keys) if key not in keys]
        self._keys = [self._keys[i] for i in kept]
        self._index = [self._index[i] for i in kept]
        self._images.offsets = [self._images.offsets[i] for i in kept]
        self._key_set -= keys

    def add_mesh(self, mesh: MeshRow) -> None:
        """Add the tracked mesh of one (subject, frame)."""
        if mesh.key in self._meshes:
            raise SchemaError(f"task {self.task!r}: mesh {mesh.key!r} added twice")
        self._meshes[mesh.key] = mesh.to_arrow_dict()

    def quarantine(self, entry: QuarantineEntry) -> None:
        """Record a refused input item (first reason per item wins)."""
        self._quarantine.setdefault(entry.item, deterministic_entry(entry))

    def close(self) -> None:
        """Finish the task's files and, in the coordinator, publish the task folder."""
        self._images.finish()
        atomic_write_bytes(
            self.tmp_dir / _PART_OFFSETS,
            json.dumps({"keys": self._keys, "offsets": self._images.offsets, "index": self._index}).encode(),
        )
        meshes = [self._meshes[k] for k in sorted(self._meshes)]
        write_table_file(self.tmp_dir / MESHES_NAME, pa.Table.from_pylist(meshes, schema=MESH_SCHEMA))
        lines = "".join(self._quarantine[k].to_json_line() + "\n" for k in sorted(self._quarantine))
        atomic_write_bytes(self.tmp_dir / QUARANTINE_NAME, lines.encode("utf-8"))
        if self.publish:
            _publish_part(self.tmp_dir, self.final_dir)

    def abort(self) -> None:
        self._images.abort()
        shutil.rmtree(self.tmp_dir, ignore_errors=True)

    def __enter__(self) -> PartWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class ShardWriter:
    """Writes ``<dataset_dir>`` (see the module docstring). Holds only paths and settings: picklable."""

    def __init__(
        self,
        dataset_dir: Path,
        info: DatasetInfo,
        max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
        compression_level: int = 3,
    ):
        self.dataset_dir = Path(dataset_dir)
        self.info = info
        self.max_shard_bytes = int(max_shard_bytes)
        self.compression_level = compression_level
        if self.dataset_dir.name != info.name:
            raise ValueError(
                f"dataset folder {self.dataset_dir} must be named after the dataset {info.name!r}"
            )
        # The coordinator: the one process that publishes parts (a pickled copy keeps this pid).
        self.coordinator_pid = os.getpid()

    @property
    def parts_dir(self) -> Path:
        return self.dataset_dir / PARTS_DIR

    def begin(self) -> None:
        """Start (or resume) writing: lock the folder for this process until ``commit`` (another writer
        gets :class:`~relightanyone.locking.OutputLockedError` and changes nothing), drop the manifest and
        temporary files; keep finished parts of the same config."""
        acquire_output_lock(self.dataset_dir)
        (self.dataset_dir / MANIFEST_NAME).unlink(missing_ok=True)
        fsync_dir(self.dataset_dir)
        stamp = self.parts_dir / _CONFIG_STAMP
        # Parts of another config, or of another format version (another row schema), are not reused.
        expected = {"config_fingerprint": self.info.config_fingerprint, "format_version": FORMAT_VERSION}
        if self.parts_dir.exists() and (not stamp.exists() or json.loads(stamp.read_text()) != expected):
            shutil.rmtree(self.parts_dir)
        self.parts_dir.mkdir(exist_ok=True)
        for tmp in [*self.dataset_dir.glob("*.tmp"), *self.parts_dir.glob("*.tmp")]:
            shutil.rmtree(tmp) if tmp.is_dir() else tmp.unlink()
        for stale in (_STAGED_LIGHTS, _STAGED_QUARANTINE):
            (self.parts_dir / stale).unlink(missing_ok=True)
        atomic_write_bytes(stamp, json.dumps(expected).encode())

    def has_part(self, task: str) -> bool:
        """Whether ``task`` finished in this or an earlier (interrupted) run."""
        return (self.parts_dir / _check_task_name(task)).is_dir()

    def part(self, task: str) -> PartWriter:
        """A writer for the rows of one task; use it as a context manager."""
        if not self.parts_dir.is_dir():
            raise RuntimeError(f"{self.dataset_dir}: call ShardWriter.begin() before writing parts")
        return PartWriter(
            self.parts_dir, task, self.compression_level, publish=os.getpid() == self.coordinator_pid
        )

    def publish(self, task: str) -> None:
        """In the coordinator, once ``task`` has returned: publish the part a worker finished for it (nothing
        to do when the coordinator wrote the part itself)."""
        if os.getpid() != self.coordinator_pid:
            raise RuntimeError(f"{self.dataset_dir}: parts are published by the coordinator process only")
        final_dir = self.parts_dir / _check_task_name(task)
        tmp_dir = self.parts_dir / f"{task}.tmp"
        if tmp_dir.is_dir():
            _publish_part(tmp_dir, final_dir)
        elif not final_dir.is_dir():
            raise RuntimeError(f"{self.dataset_dir}: task {task!r} has no finished part to publish")

    def write_lights(self, lights: Sequence[LightRow]) -> None:
        """The rig's lights (OLAT datasets), sorted by index; published by ``commit``."""
        indices = [light.index for light in lights]
        if len(set(indices)) != len(indices):
            raise SchemaError(f"{self.info.name}: light indices are not unique")
        rows = [light.to_arrow_dict() for light in sorted(lights, key=lambda light: light.index)]
        write_table_file(self.parts_dir / _STAGED_LIGHTS, pa.Table.from_pylist(rows, schema=LIGHT_SCHEMA))

    def quarantine(self, entry: QuarantineEntry) -> bool:
        """Record a refusal that belongs to no task (append-safe; deduplicated by item)."""
        return QuarantineLog(self.parts_dir / _STAGED_QUARANTINE).append(deterministic_entry(entry))

    def commit(self, progress: bool = False) -> Manifest:
        """Merge all finished parts in key order into shards, write the tables and the manifest (last)."""
        if not self.parts_dir.is_dir():
            raise RuntimeError(
                f"{self.dataset_dir}: nothing to commit; call ShardWriter.begin() and write parts first"
            )
        unpublished = sorted(p.name for p in self.parts_dir.glob("*.tmp"))
        if unpublished:  # a worker's part nobody published: its rows would be missing
            raise RuntimeError(
                f"{self.dataset_dir}: parts never published, call publish(task): {unpublished}"
            )
        parts = sorted(p for p in self.parts_dir.iterdir() if p.is_dir())
        located: list[tuple[str, int, int, list | None]] = []
        owner: dict[str, str] = {}
        for part_index, part in enumerate(parts):
            offsets = json.loads((part / _PART_OFFSETS).read_text())
            index = offsets.get("index") or [None] * len(offsets["keys"])  # absent in older parts
            for key, offset, values in zip(offsets["keys"], offsets["offsets"], index, strict=True):
                if key in owner:
                    raise SchemaError(
                        f"{self.info.name}: image key {key!r} is in tasks {owner[key]!r} and {part.name!r}"
                    )
                owner[key] = part.name
                located.append((key, part_index, offset, values))
        located.sort()
        sources = [pa.memory_map(str(part / _PART_IMAGES)) for part in parts]

        shards, index_rows = self._write_shards(located, sources, progress)
        index_entry = self._write_index(index_rows)
        meshes_entry = self._write_meshes(parts)
        lights_entry = self._publish_lights()
        quarantine_entry = self._write_quarantine(parts)
        counts = {
            "images": len(located),
            "subjects": len({r["subject"] for r in index_rows}),
            "cameras": len({r["camera"] for r in index_rows}),
            "patterns": len({r["pattern"] for r in index_rows}),
            "frames": len({(r["subject"], r["frame"]) for r in index_rows}),
            "meshes": meshes_entry.rows if meshes_entry else 0,
            "lights": lights_entry.rows if lights_entry else 0,
        }
        manifest = Manifest(
            self.info,
            counts,
            shards,
            index_entry,
            meshes_entry,
            lights_entry,
            quarantined=quarantine_entry.rows,
            quarantine=quarantine_entry,
        )
        atomic_write_bytes(self.dataset_dir / MANIFEST_NAME, manifest.dumps().encode("utf-8"))
        shutil.rmtree(self.parts_dir)
        release_output_lock(self.dataset_dir)
        return manifest

    def _entry(self, name: str, rows: int) -> FileEntry:
        path = self.dataset_dir / name
        return FileEntry(file=name, rows=rows, sha256=sha256_file(path), bytes=path.stat().st_size)

    def _write_shards(self, located, sources, progress: bool) -> tuple[list[FileEntry], list[dict]]:
        shards: list[FileEntry] = []
        index_rows: list[dict] = []
        writer: StreamFileWriter | None = None
        bar = progress_bar(
            total=len(located), desc=f"commit {self.info.name}", unit="row", disable=not progress
        )

        def finish() -> None:
            writer.finish()
            shards.append(self._entry(writer.path.name, len(writer.offsets)))

        for _key, part_index, offset, values in located:
            if writer is None:
                writer = StreamFileWriter(
                    self.dataset_dir / SHARD_PATTERN.format(len(shards)), IMAGE_SCHEMA, self.compression_level
                )
            # Rows move as encoded messages: compressed once by their task, never decoded here.
            message = read_message_at(sources[part_index], offset)
            if values is None:
                batch = pa.ipc.read_record_batch(message, IMAGE_SCHEMA)
                values = [batch.column(name)[0].as_py() for name in INDEX_COLUMNS]
            batch_offset = writer.write_message(message)
            index_rows.append(
                {
                    **dict(zip(INDEX_COLUMNS, values, strict=True)),
                    "shard": len(shards),
                    "batch_offset": batch_offset,
                }
            )
            bar.update()
            if writer.bytes_written >= self.max_shard_bytes:
                finish()
                writer = None
        if writer is not None:
            finish()
        bar.close()
        for path in self.dataset_dir.glob("images-*.arrow"):
            match = _SHARD_NAME.match(path.name)
            if match is None or int(match.group(1)) >= len(shards):  # left by an earlier, larger run
                path.unlink()
        return shards, index_rows

    def _write_index(self, index_rows: list[dict]) -> FileEntry:
        write_table_file(self.dataset_dir / INDEX_NAME, pa.Table.from_pylist(index_rows, schema=INDEX_SCHEMA))
        return self._entry(INDEX_NAME, len(index_rows))

    def _write_meshes(self, parts: Iterable[Path]) -> FileEntry | None:
        tables = [read_table_file(part / MESHES_NAME) for part in parts]
        table = pa.concat_tables(tables) if tables else MESH_SCHEMA.empty_table()
        path = self.dataset_dir / MESHES_NAME
        if table.num_rows == 0:
            path.unlink(missing_ok=True)
            return None
        keys = table.column("key").to_pylist()
        if len(set(keys)) != len(keys):
            raise SchemaError(f"{self.info.name}: a mesh (subject, frame) was written by two tasks")
        table = table.take(pc.sort_indices(table, [("key", "ascending")]))
        write_table_file(path, table.combine_chunks())
        return self._entry(MESHES_NAME, table.num_rows)

    def _publish_lights(self) -> FileEntry | None:
        staged, path = self.parts_dir / _STAGED_LIGHTS, self.dataset_dir / LIGHTS_NAME
        if not staged.exists():
            path.unlink(missing_ok=True)
            return None
        os.replace(staged, path)
        fsync_dir(self.dataset_dir)
        return self._entry(LIGHTS_NAME, read_table_file(path).num_rows)

    def _write_quarantine(self, parts: Iterable[Path]) -> FileEntry:
        entries: dict[str, QuarantineEntry] = {}
        logs = [QuarantineLog(part / QUARANTINE_NAME) for part in parts]
        logs.append(QuarantineLog(self.parts_dir / _STAGED_QUARANTINE))
        for log in logs:
            for entry in log.entries():
                entries.setdefault(entry.item, entry)
        lines = "".join(entries[item].to_json_line() + "\n" for item in sorted(entries))
        atomic_write_bytes(self.dataset_dir / QUARANTINE_NAME, lines.encode("utf-8"))
        return self._entry(QUARANTINE_NAME, len(entries))


def dataset_dirs(root: Path) -> list[Path]:
    """``root`` itself when it holds a dataset (manifest or parts), else its sub-folders that do."""
    root = Path(root)
    markers = (MANIFEST_NAME, PARTS_DIR, INDEX_NAME)
    if any((root / m).exists() for m in markers) or any(root.glob("images-*.arrow*")):
        return [root]
    return sorted(
        p
        for p in root.iterdir()
        if p.is_dir() and (any((p / m).exists() for m in markers) or any(p.glob("images-*")))
    )
