"""Shared test fixtures.

Real calibration and light-rig files live in ``../shared/fixtures/real`` beside the checkout; they are
not copied into the project. Tests that need them use the ``real_fixtures`` fixture, which skips with
the reason when that folder is absent.

Modules whose tensors are tiny run on one torch thread: ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``.
"""

from __future__ import annotations

import fcntl
import tempfile
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_REAL_FIXTURES = REPO_ROOT.parent / "shared" / "fixtures" / "real"


@pytest.fixture(scope="session")
def real_fixtures() -> Path:
    """Folder of real dataset files (Ava-256, FaceOLAT); skips the test when it is not present."""
    if not SHARED_REAL_FIXTURES.is_dir():
        pytest.skip(
            f"real fixtures not found at {SHARED_REAL_FIXTURES} (the ../shared folder beside the checkout)"
        )
    return SHARED_REAL_FIXTURES


@pytest.fixture(scope="module")
def one_torch_thread():
    """One intra-op torch thread for the module's tests, restored afterwards. Their tensors are tiny, so
    threads only add synchronisation; and the suite runs two workers on two cores, where the spinning
    OpenMP threads of oversubscribed processes slow every step many times over."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def ray_exclusive():
    """Tests that start or join Ray run one at a time on a machine (a file lock across test processes): Ray
    instances started side by side share ``/tmp/ray`` (its latest session and current-cluster files), and
    a test process's Ray then interferes with another's."""
    with open(Path(tempfile.gettempdir()) / "relightanyone-ray-tests.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield
