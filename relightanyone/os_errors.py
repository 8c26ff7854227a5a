"""Operating-system failures (a read-only or unwritable folder, a full disk, a file where a folder should be)
as expected failures: each names its path and what to do.

* :func:`check_writable` probes an output folder before a command plans any work, so a folder it cannot
  write is found in a second, not after minutes of planning or decoding.
* :func:`naming_file` gives an ``OSError`` that names no file (pyarrow's "Error writing bytes to file")
  the file that was being written.
* :func:`os_error_line` is the one line the command line prints for an ``OSError``: the path, the problem
  and the advice for its kind.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_NO_SPACE = "free space on that disk or write somewhere else, then run the command again (it resumes)"
_NOT_ALLOWED = "make it writable (permissions, owner) or write somewhere else"
# What to do about an OS error, by errno; an error of another kind is printed without advice.
OS_ERROR_ADVICE = {
    errno.ENOSPC: _NO_SPACE,
    errno.EDQUOT: _NO_SPACE,
    errno.EROFS: "the file system is read-only; write somewhere else",
    errno.EACCES: _NOT_ALLOWED,
    errno.EPERM: _NOT_ALLOWED,
    errno.ENOTDIR: "a file stands where a folder is needed; move it away or choose another path",
    errno.EISDIR: "a folder stands where a file is needed; choose another path",
    errno.ENOENT: "check the path",
}
PROBE_PREFIX = ".relightanyone-write-probe-"
# Where a command records the folder it writes (``--out``, in the click context's ``meta``), so that an OS
# error naming no file is reported with that folder.
OUTPUT_META_KEY = "relightanyone.output"


def os_error_line(error: OSError, output: Path | str | None = None) -> str:
    """``path: problem; advice`` for ``error``. The path is the error's file (``a -> b`` for a rename), or
    ``output`` (the folder the command writes) when the error names none; an error with neither a file nor
    an errno (a message of this project's own) is its message."""
    where = str(error.filename) if error.filename is not None else None
    if where is not None and error.filename2 is not None:
        where += f" -> {error.filename2}"
    if where is None and error.errno is None:
        return str(error) or type(error).__name__
    if where is None and output is not None:
        where = f"{output} (being written)"
    problem = error.strerror or str(error) or type(error).__name__
    advice = OS_ERROR_ADVICE.get(error.errno)
    text = f"{where}: {problem}" if where is not None else problem
    return f"{text}; {advice}" if advice else text


@contextmanager
def naming_file(path: Path | str) -> Iterator[None]:
    """Re-raise an ``OSError`` without a file name as one naming ``path`` (same errno, same message)."""
    try:
        yield
    except OSError as error:
        if error.filename is not None:
            raise
        raise OSError(error.errno, error.strerror or str(error), str(path)) from error


def nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (the folder a ``mkdir -p`` of ``path`` would start in)."""
    path = Path(path).absolute()
    while not path.exists() and path.parent != path:
        path = path.parent
    return path


def check_writable(folder: Path | str) -> None:
    """Raise the ``OSError`` of writing into ``folder`` (or, when it does not exist yet, the nearest existing
    folder above it, where it would be created) by creating and removing a temporary file there."""
    folder = Path(folder)
    existing = nearest_existing(folder)
    if not existing.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(existing))
    try:
        handle, probe = tempfile.mkstemp(prefix=PROBE_PREFIX, dir=existing)
    except OSError as error:
        raise OSError(error.errno, error.strerror or str(error), str(existing)) from None
    os.close(handle)
    os.unlink(probe)
