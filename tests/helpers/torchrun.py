"""Run a trainer under ``torchrun`` with two gloo processes on the CPU, from a test.

The call is pickled into a file and a small script loads and runs it in every process, so any trainer
and config (dataclasses of paths and presets) can be run data-parallel without writing its script.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

from helpers.kill_handshake import IMPORT_HELPERS

TORCHRUN_GUARD_SECONDS = 240  # a hung collective ends the test instead of the suite


def run_torchrun(module: str, function: str, config, folder: Path, processes: int = 2) -> None:
    """``module.function(config)`` in ``processes`` torchrun processes (gloo, one torch thread each)."""
    folder.mkdir(parents=True, exist_ok=True)
    call = folder / "call.pkl"
    call.write_bytes(pickle.dumps(config))
    script = folder / "run.py"
    script.write_text(
        "\n".join(
            [
                IMPORT_HELPERS,
                "import pickle",
                f"from {module} import {function}",
                f"{function}(pickle.loads(open({str(call)!r}, 'rb').read()))",
            ]
        )
        + "\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")  # two processes on two cores
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node"]
    subprocess.run(
        [*command, str(processes), str(script)], check=True, env=env, timeout=TORCHRUN_GUARD_SECONDS
    )
