"""``_stage.json``: the record a stage leaves in its output directory when its command succeeded.

The record holds the stage's config, the digest of every input, the package version and the fingerprint
made of them, the output files with their hashes, the command line, start and end time and the status
(always ``"complete"``: a failed or interrupted stage leaves no record). It is written atomically.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from relightanyone import __version__
from relightanyone.pipelines.dag.pipeline_file import StageSpec

STAGE_RECORD_NAME = "_stage.json"
STAGE_LOG_NAME = "_stage.log"
RECORD_FORMAT = 1


def live_log_path(output: Path) -> Path:
    """Where a running stage's log is written: beside its output, since some commands want an empty
    output folder; it is moved to ``<output>/_stage.log`` when the command ends."""
    return Path(output).parent / f".{Path(output).name}{STAGE_LOG_NAME}"


def attempt_path(output: Path) -> Path:
    """Beside the output (like the live log): the fingerprint of the run that last started writing into it.

    It is written before the command starts and removed when the record is written, so its presence
    means an interrupted or failed run, and its content says whether that run's partial work belongs to
    the same config and inputs (:func:`read_attempt`)."""
    return Path(output).parent / f".{Path(output).name}_stage.attempt"


def stage_lock_name(output: Path) -> str:
    """The name of the lock a runner holds while a stage writes ``output``: a file beside it (like the live
    log), since the stage's own command may lock the folder itself (:mod:`relightanyone.locking`)."""
    return f".{Path(output).name}_stage.lock"


def read_attempt(output: Path) -> str | None:
    """The fingerprint of the unfinished run that last wrote into ``output``, or None."""
    try:
        return attempt_path(output).read_text(encoding="utf-8").strip() or None
    except OSError:
        return None


def write_attempt(output: Path, fingerprint: str) -> None:
    path = attempt_path(output)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(fingerprint + "\n", encoding="utf-8")
    os.replace(temporary, path)


def package_version() -> str:

    return __version__


def stage_config(stage: StageSpec) -> dict:
    """What the stage runs: kind, arguments and environment (the interpreter path is not part of it)."""
    return {"kind": stage.kind, "args": list(stage.args), "env": dict(sorted(stage.env.items()))}


def stage_fingerprint(config: dict, input_digests: dict[str, str], version: str) -> str:
    """sha256 of the config, the input digests by path and the package version."""
    payload = json.dumps({"config": config, "inputs": input_digests, "version": version}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()


def read_record(output: Path) -> dict | None:
    """The ``_stage.json`` of ``output``; None when absent, unreadable or not a complete record."""
    try:
        record = json.loads((Path(output) / STAGE_RECORD_NAME).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(record, dict) or record.get("status") != "complete" or "outputs" not in record:
        return None
    return record


def write_record(output: Path, record: dict) -> None:
    """Write ``_stage.json`` atomically: a temporary file, fsync, then rename over the old one."""
    output = Path(output)
    handle, temporary = tempfile.mkstemp(prefix="_stage.json.", suffix=".tmp", dir=output)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            json.dump(record, stream, indent=1, sort_keys=True)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, output / STAGE_RECORD_NAME)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    directory = os.open(output, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)
