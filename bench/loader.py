"""Image encodings of the normalized format, measured: size, encode/decode time, loader throughput.

Compares 16-bit PNG, half-float EXR and raw float16 under the shards' Arrow IPC zstd compression on linear
1024x1024 face-like images (smooth shading, a highlight, sensor noise, black background, about half the
frame covered). Also measures what the per-row checksum costs a read: every row read is checked against
its xxh3-64 checksum (and its Arrow buffers validated); whole passes of the same reads without those
checks, alternating with checked passes, give the overhead, and the candidate hashes are timed on the same
bytes. Writes
``bench/results/loader.json`` with machine info. Run: ``python bench/loader.py``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import statistics
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import torch
import xxhash

from relightanyone.format.arrow_io import read_batch_at
from relightanyone.format.codecs import decode_image, decode_mask, encode_image, encode_mask
from relightanyone.format.examples import face_like_image
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import (
    IMAGE_SCHEMA,
    ROW_COLUMNS,
    DatasetInfo,
    ImageRow,
    Provenance,
    build_image_row,
    row_checksum,
)
from relightanyone.format.shards import ShardWriter
from relightanyone.format.torch_dataset import NormalizedTorchDataset, collate_rows
from relightanyone.render.camera import look_at_w2c

ENCODINGS = ("png16", "exr-half", "raw-f16")
RESULT = Path(__file__).resolve().parent / "results" / "loader.json"


def _best_ms(function, repeats: int) -> tuple[dict[str, float], object]:
    """Wall and CPU milliseconds of ``function()``: the minimum over ``repeats`` (the machine is shared, and
    the minimum is the run least disturbed by other processes)."""
    wall, cpu, result = [], [], None
    for _ in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        result = function()
        wall.append((time.perf_counter() - start_wall) * 1000.0)
        cpu.append((time.process_time() - start_cpu) * 1000.0)
    return {"wall_ms": min(wall), "cpu_ms": min(cpu), "median_wall_ms": statistics.median(wall)}, result


def _write_dataset(root: Path, encoding: str, images: list[np.ndarray], masks: list[np.ndarray]) -> Path:
    info = DatasetInfo(f"bench-{encoding}", "flat", "none", "bench", Provenance("bench", "none"), encoding)
    writer = ShardWriter(root / info.name, info)
    writer.begin()
    size = images[0].shape[0]
    K = np.array([[1.2 * size, 0, (size - 1) / 2], [0, 1.2 * size, (size - 1) / 2], [0, 0, 1]])
    with writer.part("all") as part:
        for n, (image, mask) in enumerate(zip(images, masks, strict=True)):
            part.add(
                build_image_row(
                    dataset=info.name,
                    subject="s000",
                    frame=0,
                    camera=f"cam{n:03d}",
                    pattern="full",
                    split="train",
                    K=K,
                    w2c=look_at_w2c([0.0, 0.0, 1.0], np.zeros(3), [0.0, 1.0, 0.0]),
                    image=encode_image(image, encoding),
                    image_encoding=encoding,
                    mask=encode_mask(mask),
                    width=size,
                    height=size,
                    source=f"cam{n:03d}.exr",
                    source_sha256="0" * 64,
                )
            )
    writer.commit()
    return root / info.name


def _fetch_decode_ms(dataset_dir: Path, repeats: int) -> dict[str, float]:
    """Time to read one row by key from the memory-mapped shard and decode its image and mask."""
    dataset = NormalizedDataset(dataset_dir)
    keys = dataset.keys
    dataset.decoded(keys[0])  # map the shard once
    return _best_ms(lambda: [dataset.decoded(key) for key in keys], repeats)[0] | {"rows": len(keys)}


def _decoded_unverified(dataset: NormalizedDataset, key: str) -> tuple:
    """``dataset.decoded(key)`` without the row's checks (Arrow buffer validation, checksum): the read
    as it was before rows carried a checksum."""
    position = dataset.position(key)
    shard, offset = int(dataset._shard_column[position]), int(dataset._offset_column[position])
    values = read_batch_at(dataset._map(shard), offset, IMAGE_SCHEMA).to_pylist()[0]
    row = ImageRow(**{c.name: c.from_arrow(values[c.name]) for c in ROW_COLUMNS})
    return row, decode_image(row.image, row.image_encoding), decode_mask(row.mask)


def _checked_read_ms(dataset_dir: Path, pass_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """(pass_pairs,) mean CPU ms per row of passes that fetch + decode every row with the per-row checks,
    and of passes that do the same without them, in pairs whose order alternates (checked first, then
    unchecked first). Whole passes, not single rows back to back: a row read straight after the same row
    finds its compressed bytes in cache, and a pass over all rows leaves both ways equally cold."""
    dataset = NormalizedDataset(dataset_dir)
    keys = dataset.keys
    dataset.decoded(keys[0])
    reads = {"verified": dataset.decoded, "unverified": lambda k: _decoded_unverified(dataset, k)}
    per_pass: dict[str, list[float]] = {name: [] for name in reads}
    for pair in range(pass_pairs):
        for name in list(reads) if pair % 2 == 0 else list(reads)[::-1]:
            start = time.process_time()
            for key in keys:
                reads[name](key)
            per_pass[name].append((time.process_time() - start) * 1000.0 / len(keys))
    return np.array(per_pass["verified"]), np.array(per_pass["unverified"])


def _overhead_percent(verified: np.ndarray, unverified: np.ndarray, seed: int = 0) -> dict:
    """The checks' cost in % of the unchecked read (ratio of the pass means) and its 95 % bootstrap
    interval over the pairs of passes (the two passes of a pair ran back to back)."""
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(verified), size=(2000, len(verified)))
    ratios = 100.0 * (verified[draws].mean(axis=1) / unverified[draws].mean(axis=1) - 1.0)
    low, high = np.percentile(ratios, [2.5, 97.5])
    return {
        "percent": float(100.0 * (verified.mean() / unverified.mean() - 1.0)),
        "ci95": [float(low), float(high)],
        "pass_pairs": len(verified),
    }


def _checksum_cost(dataset_dir: Path, pass_pairs: int) -> dict:
    """The checked read against the unchecked one (:func:`_checked_read_ms`), and the candidate hashes
    timed on one row's image, mask and valid bytes."""
    per_pass = _checked_read_ms(dataset_dir, pass_pairs)
    verified, unverified = (float(ms.mean()) for ms in per_pass)
    dataset = NormalizedDataset(dataset_dir)
    keys = dataset.keys
    row = dataset.row(keys[0])
    values = row.to_arrow_dict()
    data = row.image + row.mask + row.valid
    hashes = {
        "xxh3_64 of every column (chosen)": lambda: row_checksum(values),
        "zlib.crc32": lambda: zlib.crc32(data),
        "blake2b, 8-byte digest": lambda: hashlib.blake2b(data, digest_size=8).digest(),
    }
    batch = dataset.record_batch(keys[0])
    hash_ms = {name: _best_ms(f, 20)[0]["cpu_ms"] for name, f in hashes.items()}
    return {
        "encoding": row.image_encoding,
        "row_bytes_hashed": len(data),
        "cpu_ms_per_row_verified": verified,
        "cpu_ms_per_row_unverified": unverified,
        "overhead_percent": 100.0 * (verified - unverified) / unverified,
        "overhead_percent_ci95": _overhead_percent(*per_pass)["ci95"],
        "pass_pairs": pass_pairs,
        "hash_ms_per_row": hash_ms,
        "arrow_validate_ms_per_row": _best_ms(lambda: batch.validate(full=True), 20)[0]["cpu_ms"],
        "hashing_percent_of_unverified_read": {name: 100.0 * ms / unverified for name, ms in hash_ms.items()},
        "xxhash": xxhash.VERSION,
        "pyarrow": pa.__version__,
    }


def _loader_rows_per_s(dataset_dir: Path, num_workers: int, epochs: int) -> float:
    dataset = NormalizedTorchDataset(dataset_dir)
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=4,
        num_workers=num_workers,
        shuffle=True,
        persistent_workers=num_workers > 0,
        collate_fn=collate_rows,
    )
    for _ in loader:  # warm-up epoch: worker start-up and page cache
        pass
    start = time.perf_counter()
    rows = 0
    for _ in range(epochs):
        for batch in loader:
            rows += batch["image"].shape[0]
    return rows / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--images", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--loader-rounds", type=int, default=2)
    parser.add_argument("--checksum-pass-pairs", type=int, default=150)
    parser.add_argument("--out", type=Path, default=RESULT)
    args = parser.parse_args()
    torch.set_num_threads(1)

    pairs = [face_like_image(args.size, args.size, seed=n) for n in range(args.images)]
    images, masks = [p[0] for p in pairs], [p[1] for p in pairs]
    coverage = float(np.mean([m.mean() for m in masks]))
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        dataset_dirs = {}
        for encoding in ENCODINGS:
            encode, encoded = _best_ms(lambda e=encoding: encode_image(images[0], e), args.repeats)
            decode, decoded = _best_ms(lambda e=encoding, b=encoded: decode_image(b, e), args.repeats)
            lit = masks[0]
            relative = np.abs(decoded - images[0])[lit] / np.maximum(images[0][lit], 1e-3)
            dataset_dirs[encoding] = _write_dataset(Path(tmp), encoding, images, masks)
            shard_bytes = sum(p.stat().st_size for p in dataset_dirs[encoding].glob("images-*.arrow"))
            fetch = _fetch_decode_ms(dataset_dirs[encoding], args.repeats)
            results[encoding] = {
                "encoded_bytes_per_image": len(encoded),
                "shard_bytes_per_row": shard_bytes / args.images,
                "encode": encode,
                "decode": decode,
                "fetch_and_decode_all_rows": fetch,
                "fetch_and_decode_cpu_ms_per_row": fetch["cpu_ms"] / fetch["rows"],
                "max_abs_error": float(np.abs(decoded - images[0]).max()),
                "p99_relative_error_on_mask": float(np.percentile(relative, 99)),
            }
        checksum = _checksum_cost(dataset_dirs["raw-f16"], args.checksum_pass_pairs)
        # The same checks cost less of a read whose decode does more work than raw-f16's conversion.
        checksum["overhead_percent_by_encoding"] = {
            "raw-f16": {
                "percent": checksum["overhead_percent"],
                "ci95": checksum["overhead_percent_ci95"],
                "pass_pairs": args.checksum_pass_pairs,
            }
        }
        for encoding in ENCODINGS:
            if encoding != "raw-f16":
                checksum["overhead_percent_by_encoding"][encoding] = _overhead_percent(
                    *_checked_read_ms(dataset_dirs[encoding], args.checksum_pass_pairs // 3)
                )
        print("row checksum", json.dumps(checksum, indent=1), flush=True)
        mask_png = encode_mask(masks[0])
        mask_timing = {
            "bytes": len(mask_png),
            "decode": _best_ms(lambda: decode_mask(mask_png), args.repeats)[0],
        }
        # Interleaved rounds, best of them: other processes on a shared machine disturb single runs.
        for workers in (0, 2):
            for _ in range(args.loader_rounds):
                for encoding in ENCODINGS:
                    rate = _loader_rows_per_s(dataset_dirs[encoding], workers, epochs=1)
                    name = f"loader_rows_per_s_workers_{workers}"
                    results[encoding][name] = max(results[encoding].get(name, 0.0), rate)
    for encoding in ENCODINGS:
        print(encoding, json.dumps(results[encoding], indent=1), flush=True)
    fastest = min(ENCODINGS, key=lambda e: results[e]["fetch_and_decode_cpu_ms_per_row"])
    smallest = min(ENCODINGS, key=lambda e: results[e]["shard_bytes_per_row"])
    payload = {
        "benchmark": "format loader: image encodings",
        "image": {
            "height": args.size,
            "width": args.size,
            "channels": 3,
            "mask_coverage": coverage,
            "images": args.images,
            "content": "face-like linear shading, highlight, noise, black background",
        },
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "processor": platform.processor(),
            "python": sys.version.split()[0],
            "torch": torch.__version__,
            "numpy": np.__version__,
            "pyarrow": __import__("pyarrow").__version__,
            # The machine is shared; a high load average means noisy timings.
            "load_average_1_5_15_min_at_end": list(os.getloadavg()),
        },
        "mask_png": mask_timing,
        "row_checksum": checksum,
        "results": results,
        "least_cpu_per_row": fastest,
        "smallest_on_disk": smallest,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
