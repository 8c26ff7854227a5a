"""The content hash of the toolkit: hex sha256 of a file's bytes or of bytes in memory.

Dataset manifests, native source items, template meshes, expansion inputs and pipeline-stage fingerprints
all name content by this hash, so a file hashed by one of them can be compared with any other.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

# Files are read in pieces of this size, so a large shard or video is never held in memory whole.
HASH_CHUNK_BYTES = 1 << 22


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of the bytes of the file ``path``."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(HASH_CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()
