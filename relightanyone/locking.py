"""One writer per output folder: an exclusive lock held for the whole run.

Every command that owns an output folder (a dataset written by the ``ShardWriter``, an export, a training
run) takes ``<folder>/.lock`` with ``flock(LOCK_EX | LOCK_NB)`` before it
changes anything there, and keeps it until it is done. A second writer is refused at once with
:class:`OutputLockedError`, one line naming the folder and the process that holds it (pid, host and
command, which the holder writes into the lock file), and touches nothing. The kernel drops the lock
when its holder dies, SIGKILL included, so a crashed run never blocks the next one: the file stays, but
unlocked, and the next run takes it over. A run that ends normally removes the file.

A process may take the same folder again (a re-run in the same process, or a command around a writer
that also locks): the lock is kept per process and folder, and only the first taker releases it.
The lock is advisory: it keeps out writers of this toolkit, not other programs. The pipeline runner locks
each stage's output while the stage runs with a file beside it (``.<output name>_stage.lock``), since the
stage's own command may lock the folder itself.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shlex
import socket
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from relightanyone.errors import InputError

LOCK_NAME = ".lock"
_HOLDER_CHARS = 300  # of the holder's line shown in a refusal

# resolved lock file -> (pid, locked descriptor) of the locks this process holds; a forked child inherits
# the entries of its parent, which are not its own: it can neither re-take nor release them.
_HELD: dict[Path, tuple[int, int]] = {}
_HELD_LOCK = threading.Lock()


class OutputLockedError(InputError):
    """Another process is writing into the output folder."""


def holder_line() -> str:
    """What a lock file says about its holder: ``pid P on HOST: COMMAND``."""
    command = shlex.join(sys.argv).replace("\n", " ")
    return f"pid {os.getpid()} on {socket.gethostname()}: {command}"


def _open_locked(path: Path) -> int:
    """A descriptor of ``path`` locked exclusively by this process; raises OutputLockedError naming the
    holder when another process has it."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()[:_HOLDER_CHARS]
            os.close(fd)
            raise OutputLockedError(
                f"{path.parent}: another run is writing here ({holder or 'holder unknown'}); "
                f"wait for it to end or stop it, then run again"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        # The holder removes the file when it releases: a file locked after that is no longer the lock.
        try:
            current = os.stat(path)
        except FileNotFoundError:
            current = None
        opened = os.fstat(fd)
        if current is not None and (current.st_dev, current.st_ino) == (opened.st_dev, opened.st_ino):
            return fd
        os.close(fd)


def acquire_output_lock(folder: Path, name: str = LOCK_NAME) -> bool:
    """Lock ``folder`` (created if missing) for this process with the file ``name`` in it; returns False
    when this process already held it. Raises :class:`OutputLockedError` when another process holds it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    key = folder.resolve() / name
    with _HELD_LOCK:
        if _HELD.get(key, (None,))[0] == os.getpid():
            return False
        fd = _open_locked(key)
        os.ftruncate(fd, 0)
        os.pwrite(fd, (holder_line() + "\n").encode("utf-8"), 0)
        _HELD[key] = (os.getpid(), fd)
        return True


def release_output_lock(folder: Path, name: str = LOCK_NAME) -> None:
    """Remove and unlock ``folder``'s lock file ``name`` if this process holds it."""
    key = Path(folder).resolve() / name
    with _HELD_LOCK:
        pid, fd = _HELD.get(key, (None, None))
        if pid != os.getpid():
            return
        del _HELD[key]
        # Removed while still locked, so a process that opened the old file sees it is gone and retries.
        with contextlib.suppress(FileNotFoundError):
            os.unlink(key)
        os.close(fd)


@contextlib.contextmanager
def output_lock(folder: Path, name: str = LOCK_NAME) -> Iterator[None]:
    """Hold ``folder``'s lock (the file ``name`` in it) for the block (see the module docstring)."""
    taken = acquire_output_lock(folder, name)
    try:
        yield
    finally:
        if taken:
            release_output_lock(folder, name)
