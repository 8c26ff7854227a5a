"""Low-level Arrow IPC and file helpers shared by the writer, the reader and the validator.

Shards are Arrow IPC *stream* files (what Hugging Face ``datasets.Dataset.from_file`` and
``pyarrow.ipc.open_stream`` read), compressed with zstd, one row per record batch. The byte offset of every
record batch is recorded at write time, so a single row is read by seeking to its message in the memory map
(``read_batch_at``) without scanning the stream.
"""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow as pa

from relightanyone.os_errors import naming_file

ZSTD_LEVEL = 3
# The end-of-stream marker of the IPC stream format: continuation token, then a zero metadata length.
STREAM_END = b"\xff\xff\xff\xff\x00\x00\x00\x00"


def ipc_write_options(compression_level: int = ZSTD_LEVEL) -> pa.ipc.IpcWriteOptions:
    # Single-threaded compression keeps the writer simple to reason about; bytes are identical either way.
    return pa.ipc.IpcWriteOptions(
        compression=pa.Codec("zstd", compression_level=compression_level), use_threads=False
    )


def fsync_dir(path: Path) -> None:
    """Make a rename inside ``path`` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via ``path.tmp``, fsync, rename: readers see the old file or the new one."""
    tmp = path.with_name(path.name + ".tmp")
    with naming_file(tmp), open(tmp, "wb") as handle:  # a failed write (a full disk) names no file
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


class StreamFileWriter:
    """Writes one Arrow IPC stream file row batch by row batch, remembering each batch's byte offset.

    The file is written under ``<path>.tmp`` and moved into place by ``finish`` (after fsync), so a killed
    process leaves only a ``.tmp`` file behind. Rows come either as record batches (``write``, encoded and
    compressed here) or as already encoded messages of another stream with the same schema
    (``write_message``, copied byte for byte: merging parts into shards does not recompress). One file
    uses one of the two; the bytes are the same either way.
    """

    def __init__(self, path: Path, schema: pa.Schema, compression_level: int = ZSTD_LEVEL):
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + ".tmp")
        self.schema = schema
        self.compression_level = compression_level
        self._sink = pa.OSFile(str(self.tmp_path), "wb")
        self._writer: pa.ipc.RecordBatchStreamWriter | None = None  # created by the first ``write``
        self._copying = False
        self.offsets: list[int] = []

    @property
    def bytes_written(self) -> int:
        return self._sink.tell()

    def write(self, batch: pa.RecordBatch) -> int:
        """Append one record batch; returns the offset to pass to ``read_batch_at``."""
        if self._copying:
            raise RuntimeError(f"{self.path}: write() after write_message(); use one of the two per file")
        if self._writer is None:
            self._writer = pa.ipc.new_stream(
                self._sink, self.schema, options=ipc_write_options(self.compression_level)
            )
        offset = self._sink.tell()
        with naming_file(self.tmp_path):  # pyarrow's write errors (a full disk) name no file
            self._writer.write_batch(batch)
        self.offsets.append(offset)
        return offset

    def write_message(self, message: pa.ipc.Message) -> int:
        """Append an encoded record-batch message (from :func:`read_message_at`); returns its offset."""
        if self._writer is not None:
            raise RuntimeError(f"{self.path}: write_message() after write(); use one of the two per file")
        if message.type != "record batch":
            raise ValueError(f"{self.path}: expected a record batch message, got a {message.type} message")
        if not self._copying:
            self._sink.write(self.schema.serialize())
            self._copying = True
        offset = self._sink.tell()
        with naming_file(self.tmp_path):
            self._sink.write(message.serialize())
        self.offsets.append(offset)
        return offset

    def finish(self) -> None:
        """Close the stream, fsync it and rename it to its final name."""
        with naming_file(self.tmp_path):
            if self._copying:
                self._sink.write(STREAM_END)
            else:
                if self._writer is None:  # an empty stream: the schema and the end marker
                    self._writer = pa.ipc.new_stream(
                        self._sink, self.schema, options=ipc_write_options(self.compression_level)
                    )
                self._writer.close()
            self._sink.flush()
            self._sink.close()
        with open(self.tmp_path, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(self.tmp_path, self.path)
        fsync_dir(self.path.parent)

    def abort(self) -> None:
        """Drop the partial file."""
        try:
            if self._writer is not None:
                self._writer.close()
            self._sink.close()
        except (OSError, pa.ArrowException):
            pass
        self.tmp_path.unlink(missing_ok=True)


def write_table_file(path: Path, table: pa.Table, max_rows_per_batch: int = 65536) -> None:
    """Write a whole table as one atomic IPC stream file (deterministic for the same table)."""
    writer = StreamFileWriter(path, table.schema)
    try:
        for batch in table.to_batches(max_chunksize=max_rows_per_batch):
            writer.write(batch)
        writer.finish()
    except BaseException:
        writer.abort()
        raise


def read_message_at(source: pa.MemoryMappedFile, offset: int) -> pa.ipc.Message:
    """The encoded record-batch message starting at ``offset`` of a stream file (the first one is preceded
    by the schema message, which is skipped); its buffers stay compressed."""
    source.seek(offset)
    message = pa.ipc.read_message(source)
    if message.type == "schema":
        message = pa.ipc.read_message(source)
    if message.type != "record batch":
        raise pa.ArrowInvalid(f"expected a record batch at byte {offset}, found a {message.type} message")
    return message


def read_batch_at(source: pa.MemoryMappedFile, offset: int, schema: pa.Schema) -> pa.RecordBatch:
    """The record batch whose message starts at ``offset`` of a stream file (see :func:`read_message_at`)."""
    return pa.ipc.read_record_batch(read_message_at(source, offset), schema)


def read_table_file(path: Path) -> pa.Table:
    """Read a whole IPC stream file (memory-mapped)."""
    return pa.ipc.open_stream(pa.memory_map(str(path))).read_all()
