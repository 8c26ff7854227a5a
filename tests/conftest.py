"""Shared test fixtures.

Real calibration and light-rig files live in ``../shared/fixtures/real`` beside the checkout; they are
not copied into the project. Tests that need them use the ``real_fixtures`` fixture, which skips with
the reason when that folder is absent.
"""

from __future__ import annotations

from pathlib import Path

import pytest

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
