"""An ingest whose pool workers stop inside their task, for the tests that kill the coordinator.

A worker process imports this module when it unpickles :func:`held_subject_task`, the task function a
child ingest script puts in place of the real one. The task writes the subject's rows as usual, but
before its part is finished it prints ``BUSY`` and blocks opening the FIFO named by ``RELEASE_ENV`` for
reading, until the test opens it for writing. A worker that survived its coordinator would then finish
the part. Without that variable the tasks run as usual (a re-run).
"""

from __future__ import annotations

import os
import textwrap
from unittest import mock

from helpers.kill_handshake import IMPORT_HELPERS
from relightanyone.format.shards import PartWriter
from relightanyone.ingest.subject_task import run_subject_task

RELEASE_ENV = "HELD_WORKERS_RELEASE_FIFO"
BUSY = "BUSY"

# Ingests the capture at argv[1] into argv[2] with two pool workers whose tasks are held (python -c SCRIPT,
# or a pipeline stage running it as a file).
HELD_INGEST_SCRIPT = IMPORT_HELPERS + textwrap.dedent(
    """
    from pathlib import Path
    from helpers.custom_capture import ingest
    from helpers.held_workers import held_subject_task
    from relightanyone.ingest import runner

    if __name__ == "__main__":  # not when a worker imports the file as its parent's main module
        runner.run_subject_task = held_subject_task
        ingest(Path(sys.argv[1]), Path(sys.argv[2]), workers=2)
        print("DONE", flush=True)
    """
)


def held_subject_task(writer, settings, task):
    """``run_subject_task`` whose part waits for the release FIFO before it is finished (without
    ``RELEASE_ENV``, the plain task)."""
    if RELEASE_ENV not in os.environ:
        return run_subject_task(writer, settings, task)
    close = PartWriter.close

    def close_when_released(part: PartWriter) -> None:
        os.write(1, f"{BUSY}\n".encode())  # one write: the two workers' lines must not interleave
        with open(os.environ[RELEASE_ENV], "rb") as release:  # blocks until the test opens it for writing
            release.read()
        close(part)

    with mock.patch.object(PartWriter, "close", close_when_released):
        return run_subject_task(writer, settings, task)


def release(fifo: str | os.PathLike) -> None:
    """Let every held worker that still lives go on (nothing happens when none is waiting)."""
    try:
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
    except OSError:  # ENXIO: no worker has the FIFO open, none is alive to release
        return
    os.close(fd)
