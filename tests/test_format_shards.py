"""Writing and reading normalized datasets: round trip, key lookup, determinism, rollover, interop."""

from __future__ import annotations

import concurrent.futures
import hashlib
import multiprocessing
from pathlib import Path

import datasets
import numpy as np
import pyarrow as pa
import pytest

from relightanyone.format import arrow_io
from relightanyone.format.codecs import decode_image
from relightanyone.format.examples import example_rows
from relightanyone.format.examples import write_example_dataset as write_demo
from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
from relightanyone.format.schema import (
    IMAGE_SCHEMA,
    DatasetInfo,
    Provenance,
    QuarantineEntry,
    SchemaError,
)
from relightanyone.format.shards import QuarantineLog, ShardWriter

SUBJECTS = ("s000", "s001", "s002")


def _info(name: str = "demo") -> DatasetInfo:
    return DatasetInfo(name, "olat", "flame", "2 OLAT lights", Provenance("FaceOLAT", "research"), "cfg-1")


def _digests(dataset_dir: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(dataset_dir.iterdir())}


def test_round_trip_rows_tables_and_filters(tmp_path):
    dataset = NormalizedDataset(write_demo(tmp_path))
    originals = {r.key: r for s in SUBJECTS for r in example_rows("demo", (s,), 2, ("full", "olat-000"))}
    assert dataset.keys == sorted(originals) and len(dataset) == 12
    for key, original in originals.items():
        row = dataset.row(key)
        assert row.image == original.image and row.mask == original.mask
        assert np.array_equal(row.K, original.K) and row.source_sha256 == original.source_sha256
    assert dataset.subjects == list(SUBJECTS) and dataset.cameras == ["cam00", "cam01"]
    assert dataset.patterns == ["full", "olat-000"] and dataset.splits == ["train"]
    assert [r.key for r in dataset.rows(subjects="s001", patterns=["full"])] == [
        "demo/s001/000000/cam00/full",
        "demo/s001/000000/cam01/full",
    ]
    assert [light["index"] for light in dataset.lights()] == [0, 1]
    assert dataset.meshes()["s002/000000"].shape == (4, 3) and dataset.meshes()["s002/000000"][0, 0] == 2
    assert [e.item for e in dataset.quarantine()] == [f"{s}/cam09" for s in SUBJECTS]
    assert dataset.manifest.counts["images"] == 12 and dataset.manifest.quarantined == 3
    _, image, mask = dataset.decoded(dataset.keys[0])
    assert image.shape == (32, 24, 3) and mask.shape == (32, 24)
    with pytest.raises(KeyError, match="no image row"):
        dataset.row("demo/nobody/000000/cam00/full")


def test_row_lookup_reads_exactly_one_record_batch(tmp_path, monkeypatch):
    dataset = NormalizedDataset(write_demo(tmp_path, max_shard_bytes=20_000))
    assert len(dataset.manifest.shards) > 1
    calls = []
    original = arrow_io.read_batch_at

    def counting(source, offset, schema):
        calls.append(offset)
        return original(source, offset, schema)

    monkeypatch.setattr("relightanyone.format.reader.read_batch_at", counting)
    last = dataset.keys[-1]
    assert dataset.row(last).key == last
    assert len(calls) == 1 and list(dataset._maps) == [len(dataset.manifest.shards) - 1]


def test_bytes_are_deterministic_whatever_the_task_order(tmp_path):
    first = write_demo(tmp_path / "a", task_order=SUBJECTS)
    second = write_demo(tmp_path / "b", task_order=tuple(reversed(SUBJECTS)))
    assert _digests(first) == _digests(second)
    assert not (first / "_parts").exists()


def test_rollover_makes_several_shards_in_key_order(tmp_path):
    dataset = NormalizedDataset(write_demo(tmp_path, max_shard_bytes=20_000))
    shards = dataset.manifest.shards
    assert len(shards) >= 3 and sum(s.rows for s in shards) == 12
    keys = []
    for shard in shards:
        keys += (
            pa.ipc.open_stream(pa.memory_map(str(dataset.path / shard.file)))
            .read_all()
            .column("key")
            .to_pylist()
        )
    assert keys == sorted(keys) == dataset.keys


def test_shards_open_with_plain_pyarrow_and_hugging_face(tmp_path):
    dataset_dir = write_demo(tmp_path)
    shard = dataset_dir / "images-00000.arrow"
    table = pa.ipc.open_stream(pa.memory_map(str(shard))).read_all()
    assert table.schema.equals(IMAGE_SCHEMA, check_metadata=True) and table.num_rows == 12
    assert table.schema.metadata[b"schema_version"] == b"2"
    hf = datasets.Dataset.from_file(str(shard))
    assert hf.num_rows == 12 and hf[3]["key"] == table.column("key")[3].as_py()
    first = hf[0]
    assert decode_image(first["image"], first["image_encoding"]).shape == (32, 24, 3)
    assert datasets.Dataset.from_file(str(dataset_dir / "meshes.arrow")).num_rows == 3


def test_resume_keeps_finished_parts_and_refuses_duplicate_keys(tmp_path):
    writer = ShardWriter(tmp_path / "demo", _info())
    writer.begin()
    with writer.part("s000") as part:
        for row in example_rows("demo", ("s000",), 1):
            part.add(row)
    with pytest.raises(RuntimeError, match="boom"), writer.part("s001") as part:
        part.add(example_rows("demo", ("s001",), 1)[0])
        raise RuntimeError("boom")
    writer.begin()  # a second run of the same config
    assert writer.has_part("s000") and not writer.has_part("s001")
    with pytest.raises(IncompleteDatasetError, match="incomplete"):
        NormalizedDataset(tmp_path / "demo")
    with writer.part("dup") as part:
        part.add(example_rows("demo", ("s000",), 1)[0])
    with pytest.raises(SchemaError, match="is in tasks 'dup' and 's000'"):
        writer.commit()
    changed = ShardWriter(
        tmp_path / "demo", DatasetInfo("demo", "olat", "flame", "", Provenance("x", "y"), "cfg-2")
    )
    changed.begin()
    assert not changed.has_part("s000")


def test_quarantine_log_is_deduplicated_and_survives_a_torn_line(tmp_path):
    log = QuarantineLog(tmp_path / "quarantine.jsonl")
    entry = QuarantineEntry("s0/cam1", "raw/s0/cam1.cr2", "no colour chart", "ingest")
    assert log.append(entry) and not log.append(entry)
    with open(log.path, "a") as handle:
        handle.write('{"item": "s0/ca')  # a kill in the middle of an append
    assert log.entries() == [entry]
    second = QuarantineEntry("s0/cam2", "raw/s0/cam2.cr2", "blurred", "ingest")
    assert log.append(second)
    assert log.entries() == [entry, second]


def test_reader_refuses_a_truncated_or_missing_shard(tmp_path):
    dataset_dir = write_demo(tmp_path, max_shard_bytes=20_000)
    shard = dataset_dir / "images-00001.arrow"
    shard.write_bytes(shard.read_bytes()[:-10])
    with pytest.raises(IncompleteDatasetError, match=r"differ in size.*images-00001.arrow"):
        NormalizedDataset(dataset_dir)
    shard.unlink()
    with pytest.raises(IncompleteDatasetError, match=r"missing: \['images-00001.arrow'\]"):
        NormalizedDataset(dataset_dir)


def _write_task(writer: ShardWriter, subject: str) -> str:
    with writer.part(subject) as part:
        for row in example_rows(writer.info.name, (subject,), cameras=2):
            part.add(row)
    return subject


def test_parts_from_worker_processes_give_the_bytes_of_a_sequential_run(tmp_path):
    subjects = ("s000", "s001", "s002", "s003")
    digests = []
    for run, parallel in (("sequential", False), ("processes", True)):
        writer = ShardWriter(tmp_path / run / "demo", _info(), max_shard_bytes=15_000)
        writer.begin()
        if parallel:
            # fork starts fast; the writer still travels to the workers pickled, as it would to Ray tasks
            context = multiprocessing.get_context("fork")
            with concurrent.futures.ProcessPoolExecutor(2, mp_context=context) as pool:
                assert sorted(pool.map(_write_task, [writer] * 4, reversed(subjects))) == list(subjects)
            assert not any(writer.has_part(s) for s in subjects)  # only this process publishes
            for subject in subjects:
                writer.publish(subject)
        else:
            for subject in subjects:
                _write_task(writer, subject)
        writer.commit()
        digests.append(_digests(tmp_path / run / "demo"))
    assert digests[0] == digests[1] and len(digests[0]) >= 4


def test_withdrawn_rows_are_left_out_of_the_commit(tmp_path):
    writer = ShardWriter(tmp_path / "demo", _info())
    writer.begin()
    rows = example_rows("demo", ("s000",), 3, ("full",))
    with writer.part("s000") as part:
        for row in rows:
            part.add(row)
        part.withdraw({rows[1].key})
        part.add(rows[1])  # a withdrawn key is free again
        part.withdraw({rows[0].key, rows[1].key})
    writer.commit()
    dataset = NormalizedDataset(tmp_path / "demo")
    assert dataset.keys == [rows[2].key] and dataset.row(rows[2].key).image == rows[2].image
