"""Reading a normalized dataset.

``NormalizedDataset(path)`` checks that ``manifest.json`` exists and that every file it lists is present
with the listed size (hashes are checked by ``validate``), reads the
small ``index.arrow`` (key, subject, frame, camera, pattern, split, shard, byte offset of the row's record
batch) and builds a key -> position dict. ``row(key)`` then memory-maps the shard (``pa.memory_map``) once
and reads just that row's record batch at its offset: O(1) in the number of rows. Every row read is checked
against its checksum (``schema.row_checksum``), so corrupted bytes raise an ``InputError`` naming the
shard file and the row instead of returning different pixels. Shards are Arrow IPC
*stream* files, so ``pyarrow.ipc.open_stream`` and Hugging Face ``datasets.Dataset.from_file`` open them as
they are.

The object is picklable: memory maps are opened lazily and dropped on pickling, so each DataLoader worker
maps the files itself.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from relightanyone.errors import InputError, RelightAnyoneError
from relightanyone.format.arrow_io import read_batch_at, read_table_file
from relightanyone.format.codecs import decode_image, decode_mask
from relightanyone.format.schema import (
    IMAGE_SCHEMA,
    INDEX_NAME,
    LIGHTS_NAME,
    MANIFEST_NAME,
    MESHES_NAME,
    QUARANTINE_NAME,
    ImageRow,
    Manifest,
    QuarantineEntry,
    SchemaError,
)


class IncompleteDatasetError(RelightAnyoneError, RuntimeError):
    """The folder is not a complete dataset (no manifest, or files it lists are missing)."""


class CorruptRowError(InputError):
    """A stored row cannot be read or does not match its checksum; the message names the shard and row."""


def load_manifest(dataset_dir: Path) -> Manifest:
    """Parse ``<dataset_dir>/manifest.json``; raises ``IncompleteDatasetError`` when it is absent."""
    path = Path(dataset_dir) / MANIFEST_NAME
    if not path.exists():
        raise IncompleteDatasetError(
            f"{dataset_dir}: no {MANIFEST_NAME}, so the dataset is incomplete (an interrupted write?); "
            "re-run the command that produced it"
        )
    try:
        values = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise SchemaError(f"{path}: not valid JSON ({error})") from None
    return Manifest.from_json(values, where=str(path))


class _IndexValues:
    """A read-only attribute of a :class:`NormalizedDataset`: the sorted distinct values of one index column."""

    def __init__(self, column: str):
        self.column = column

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, dataset: NormalizedDataset | None, owner: type) -> Any:
        return self if dataset is None else dataset._distinct(self.column)

    def __set__(self, dataset: NormalizedDataset, value: Any) -> None:
        raise AttributeError(f"{self.name} is read from the index and cannot be set")


class NormalizedDataset:
    """A complete normalized dataset folder; rows by key in O(1), filters over the index."""

    def __init__(self, path: Path | str):
        self.path = Path(path)
        self.manifest = load_manifest(self.path)
        needed = [*self.manifest.shards, self.manifest.index]
        needed += [e for e in (self.manifest.meshes, self.manifest.lights) if e is not None]
        missing = [e.file for e in needed if not (self.path / e.file).exists()]
        if missing:
            raise IncompleteDatasetError(f"{self.path}: files listed in the manifest are missing: {missing}")
        # Sizes are cheap to check and catch truncation; `relightanyone validate` also checks the hashes.
        resized = [e.file for e in needed if (self.path / e.file).stat().st_size != e.bytes]
        if resized:
            raise IncompleteDatasetError(
                f"{self.path}: files differ in size from the manifest (truncated?): {resized}; "
                f"run `relightanyone validate {self.path}`"
            )
        self.index = read_table_file(self.path / INDEX_NAME)
        if self.index.num_rows != self.manifest.index.rows:
            raise IncompleteDatasetError(
                f"{self.path / INDEX_NAME}: {self.index.num_rows} rows, the manifest says {self.manifest.index.rows}"
            )
        self._keys = self.index.column("key").to_pylist()
        self._position = {key: i for i, key in enumerate(self._keys)}
        self._shard_column = self.index.column("shard").to_numpy()
        self._offset_column = self.index.column("batch_offset").to_numpy()
        self._maps: dict[int, pa.MemoryMappedFile] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_maps"] = {}
        return state

    @property
    def name(self) -> str:
        return self.manifest.info.name

    def __len__(self) -> int:
        return self.index.num_rows

    def __contains__(self, key: str) -> bool:
        return key in self._position

    @property
    def keys(self) -> list[str]:
        """All image keys, sorted."""
        return list(self._keys)

    def position(self, key: str) -> int:
        """The row of ``key`` in ``index``."""
        position = self._position.get(key)
        if position is None:
            raise KeyError(f"{self.path}: no image row with key {key!r}")
        return position

    def _distinct(self, column: str) -> list[str]:
        return sorted(set(self.index.column(column).to_pylist()))

    subjects = _IndexValues("subject")
    cameras = _IndexValues("camera")
    patterns = _IndexValues("pattern")
    splits = _IndexValues("split")

    def shard_path(self, shard: int) -> Path:
        return self.path / self.manifest.shards[shard].file

    def _map(self, shard: int) -> pa.MemoryMappedFile:
        if shard not in self._maps:
            self._maps[shard] = pa.memory_map(str(self.shard_path(shard)))
        return self._maps[shard]

    def record_batch(self, key: str) -> pa.RecordBatch:
        """The one-row record batch of ``key`` (zero-copy where the data is not compressed; not checked
        against the row's checksum: :meth:`row` does that)."""
        position = self.position(key)
        shard, offset = int(self._shard_column[position]), int(self._offset_column[position])
        try:
            batch = read_batch_at(self._map(shard), offset, IMAGE_SCHEMA)
            # Offsets and lengths checked before any value is touched: a flipped byte there must not
            # send a read past a buffer (a few µs for one row).
            batch.validate(full=True)
            return batch
        except (pa.ArrowException, OSError) as error:
            raise CorruptRowError(
                f"{self.shard_path(shard)}: row {key!r} at byte {offset} cannot be read ({error}); the shard "
                f"is corrupted: run `relightanyone validate {self.path}`, then restore or re-ingest it"
            ) from None

    def row(self, key: str) -> ImageRow:
        """The image row of ``key`` (image and mask still encoded), checked against its checksum."""
        values = self.record_batch(key).to_pylist()[0]
        try:
            return ImageRow.from_arrow_dict(values)
        except SchemaError as error:
            shard = self.shard_path(int(self._shard_column[self.position(key)]))
            raise CorruptRowError(f"{shard}: {error}") from None

    def decoded(self, key: str) -> tuple[ImageRow, np.ndarray, np.ndarray]:
        """``(row, image (H, W, 3) float32 linear, mask (H, W) float32 in [0, 1])``; the row's valid
        pixels are ``row.valid_pixels()``."""
        row = self.row(key)
        return row, decode_image(row.image, row.image_encoding), decode_mask(row.mask)

    def select(
        self,
        subjects: list[str] | str | None = None,
        cameras: list[str] | str | None = None,
        patterns: list[str] | str | None = None,
        splits: list[str] | str | None = None,
        frames: list[int] | int | None = None,
    ) -> list[str]:
        """Keys (sorted) whose fields are in the given values; ``None`` means any."""
        mask = np.ones(len(self), dtype=bool)
        for column, wanted in (
            ("subject", subjects),
            ("camera", cameras),
            ("pattern", patterns),
            ("split", splits),
            ("frame", frames),
        ):
            if wanted is None:
                continue
            wanted = [wanted] if isinstance(wanted, (str, int)) else list(wanted)
            mask &= np.isin(np.asarray(self.index.column(column).to_pylist(), dtype=object), wanted)
        return [key for key, keep in zip(self._keys, mask, strict=True) if keep]

    def rows(self, **filters: Any) -> Iterator[ImageRow]:
        """Image rows in key order, filtered as in ``select``."""
        for key in self.select(**filters):
            yield self.row(key)

    def lights(self) -> list[dict[str, Any]]:
        """``lights.arrow`` rows (index, name, position_m, intensity_rgb, pattern); empty for flat datasets."""
        if self.manifest.lights is None:
            return []
        return read_table_file(self.path / LIGHTS_NAME).to_pylist()

    def meshes(self) -> dict[str, np.ndarray]:
        """Mesh key ("<subject>/<frame:06d>") -> vertices (V, 3) float32."""
        if self.manifest.meshes is None:
            return {}
        table = read_table_file(self.path / MESHES_NAME)
        out = {}
        for i, key in enumerate(table.column("key").to_pylist()):
            flat = table.column("vertices")[i].values.to_numpy(zero_copy_only=False)
            out[key] = flat.astype(np.float32).reshape(-1, 3)
        return out

    def quarantine(self) -> list[QuarantineEntry]:
        """Refused input items."""
        path = self.path / QUARANTINE_NAME
        if not path.exists():
            return []
        return [
            QuarantineEntry(**json.loads(line))
            for line in path.read_text("utf-8").splitlines()
            if line.strip()
        ]
