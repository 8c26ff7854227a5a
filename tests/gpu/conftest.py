"""The GPU tests: every test in this folder needs CUDA and is skipped, with the reason, without it.

Run them on a machine with a GPU: ``python -m pytest tests/gpu -q`` (and ``python bench/gpu.py``).
"""

from __future__ import annotations

import pytest
import torch

NO_CUDA = "CUDA is not available on this machine (tests/gpu run on a GPU)"


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason=NO_CUDA)
    for item in items:
        if "tests/gpu/" in item.nodeid.replace("\\", "/") or item.nodeid.startswith("gpu/"):
            item.add_marker(skip)
            item.add_marker(pytest.mark.gpu)
