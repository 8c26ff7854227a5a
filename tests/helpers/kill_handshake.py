"""Killing a child process exactly where it says it is: the handshake of the SIGKILL/resume tests.

The child is a Python script the test writes. At the point to interrupt it calls :func:`block_until_killed`,
which prints a marker line and then blocks reading its stdin, a pipe the parent holds open and never writes
to. The parent (:func:`kill_at`) reads the child's stdout up to that line and sends SIGKILL, so the kill
lands at that point on a loaded machine as on an idle one: no polling, no sleeps. Should the parent go away
instead, the child's stdin closes and it exits with an error rather than finishing its work.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

TESTS_DIR = Path(__file__).resolve().parents[1]
# Only a hang guard: a child that neither reaches its marker nor ends within this is killed, and the test
# fails saying so. Reaching the marker sooner or later is never asserted.
HANG_GUARD_SECONDS = 900
# How long the processes of a killed run may take to die. Death is polled for, never timed: only a
# process still alive after this fails a test.
DEATH_GUARD_SECONDS = 10

# The first lines of a child script: makes ``helpers`` importable as in the tests.
IMPORT_HELPERS = f"import sys; sys.path.insert(0, {str(TESTS_DIR)!r})\n"


def block_until_killed(marker: str) -> None:
    """In the child: print ``marker`` on its own line, then wait for the parent's SIGKILL."""
    print(marker, flush=True)
    sys.stdin.readline()
    sys.exit(f"stdin closed while waiting to be killed at {marker!r}")


def start_python(source: str, *args: object, env: dict[str, str] | None = None) -> subprocess.Popen:
    """Run ``python -c source args...`` with stdin and stdout as pipes (text), ready for :func:`kill_at`."""
    return subprocess.Popen(
        [sys.executable, "-c", source, *(str(a) for a in args)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
    )


def kill_at(
    process: subprocess.Popen, marker: str, count: int = 1, before_kill: Callable[[], None] | None = None
) -> list[str]:
    """Read ``process``'s stdout up to the ``count``-th line ``marker``, call ``before_kill``, then SIGKILL
    ``process`` (only it); returns the other lines.

    Fails when the child ends (or the hang guard kills it) before printing the markers; the child is
    killed and reaped in every case.
    """
    guard = threading.Timer(HANG_GUARD_SECONDS, process.kill)
    guard.start()
    lines = []
    seen = 0
    try:
        for line in process.stdout:
            if line.rstrip("\n") == marker:
                seen += 1
                if seen == count:
                    if before_kill is not None:
                        before_kill()
                    break
                continue
            lines.append(line.rstrip("\n"))
        else:
            raise AssertionError(
                f"the child ended before {marker!r} (exit status {process.wait()}, "
                f"hang guard {HANG_GUARD_SECONDS} s); its output:\n" + "\n".join(lines)
            )
    finally:
        guard.cancel()
        process.kill()
        process.wait()
        process.stdin.close()
        process.stdout.close()
    assert process.returncode == -signal.SIGKILL
    return lines


def finish(process: subprocess.Popen, marker: str) -> list[str]:
    """Wait for a child that is not interrupted; fails unless it exits 0 with ``marker`` as its last line.
    Returns its output lines."""
    try:
        output, _ = process.communicate(timeout=HANG_GUARD_SECONDS)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    lines = output.splitlines()
    assert process.returncode == 0 and lines and lines[-1] == marker, (process.returncode, output)
    return lines


def _stat_fields(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (state first), or None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return text[text.rindex(")") + 2 :].split()


def descendants(pid: int) -> dict[int, str]:
    """Every living descendant of ``pid``: pid -> its start time (to tell it from a later process that
    reuses the pid)."""
    children: dict[int, list[int]] = {}
    started: dict[int, str] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        fields = _stat_fields(int(entry.name))
        if fields is not None:
            children.setdefault(int(fields[1]), []).append(int(entry.name))
            started[int(entry.name)] = fields[19]
    found: dict[int, str] = {}
    stack = [pid]
    while stack:
        for child in children.get(stack.pop(), []):
            found[child] = started[child]
            stack.append(child)
    return found


def alive(processes: dict[int, str]) -> list[int]:
    """The pids of ``processes`` (pid -> start time) still running (a zombie counts as dead)."""
    living = []
    for pid, start in processes.items():
        fields = _stat_fields(pid)
        if fields is not None and fields[19] == start and fields[0] not in ("Z", "X"):
            living.append(pid)
    return living


def wait_until_dead(processes: dict[int, str]) -> list[int]:
    """Poll until every process of ``processes`` has died or :data:`DEATH_GUARD_SECONDS` have passed;
    returns the pids still alive (empty when all died)."""
    deadline = time.monotonic() + DEATH_GUARD_SECONDS
    while (living := alive(processes)) and time.monotonic() < deadline:
        time.sleep(0.05)
    return living


def kill_all(processes: dict[int, str]) -> None:
    """SIGKILL those of ``processes`` still alive (clean-up after a failed test)."""
    for pid in alive(processes):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
