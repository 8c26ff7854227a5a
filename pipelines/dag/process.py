"""Running one stage's command in a subprocess, its output shown live and kept in a log file.

The child's stdout and stderr share one pipe, so progress bars and messages keep their order; every
chunk goes to the terminal (unless quiet) and to the log. On Linux the child is asked to die with the
runner (``PR_SET_PDEATHSIG``): a runner killed with SIGKILL leaves no orphan writing into the output
directory while the next run starts the stage again; the stage's own pool workers die with the stage
(:mod:`relightanyone.parallel`).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import BinaryIO

from relightanyone.parallel import die_with_parent

READ_CHUNK_BYTES = 1 << 16


def stage_argv(kind: str, args: tuple[str, ...]) -> list[str]:
    """The argv that runs a stage: ``relightanyone ARGS`` with this interpreter, or the command as given."""
    if kind == "run":
        return [sys.executable, "-m", "relightanyone", *args]
    return list(args)


def run_with_log(
    argv: list[str], log: BinaryIO, env: dict[str, str], echo: BinaryIO | None, cwd: Path | None = None
) -> int:
    """Run ``argv`` to completion, copying its merged output to ``log`` and ``echo``; returns the exit status.

    Raises FileNotFoundError naming the executable when it does not exist.
    """
    child_env = {**os.environ, "PYTHONUNBUFFERED": "1", **env}
    try:
        process = subprocess.Popen(
            argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=child_env,
            cwd=cwd,
            # Between fork and exec; the runner waits for the child in the thread that started it.
            preexec_fn=die_with_parent if sys.platform.startswith("linux") else None,
        )
    except FileNotFoundError:
        raise FileNotFoundError(
            f"executable {argv[0]!r} not found; check the command: of the stage"
        ) from None
    assert process.stdout is not None
    fd = process.stdout.fileno()
    try:
        while chunk := os.read(fd, READ_CHUNK_BYTES):
            log.write(chunk)
            if echo is not None:
                echo.write(chunk)
                echo.flush()
    except BaseException:
        # Ctrl-C or an error in the runner: stop the child too, so nothing keeps writing.
        process.kill()
        process.wait()
        raise
    finally:
        process.stdout.close()
    return process.wait()
