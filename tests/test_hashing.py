"""The toolkit's content hash: sha256 of bytes and of files, whatever their size."""

from __future__ import annotations

import hashlib

from relightanyone.hashing import HASH_CHUNK_BYTES, sha256_bytes, sha256_file

ABC_SHA256 = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"  # FIPS 180-2 example


def test_sha256_of_bytes_and_files_known_value(tmp_path):
    assert sha256_bytes(b"abc") == ABC_SHA256
    (tmp_path / "abc.txt").write_bytes(b"abc")
    assert sha256_file(tmp_path / "abc.txt") == ABC_SHA256
    assert sha256_file(str(tmp_path / "abc.txt")) == ABC_SHA256


def test_a_file_longer_than_one_chunk_hashes_like_its_bytes(tmp_path):
    data = bytes(range(256)) * (HASH_CHUNK_BYTES // 256) + b"tail"  # one full chunk and a few bytes more
    (tmp_path / "big.bin").write_bytes(data)
    assert sha256_file(tmp_path / "big.bin") == sha256_bytes(data) == hashlib.sha256(data).hexdigest()
