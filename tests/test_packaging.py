"""What a non-editable install carries: every compiled-kernel source and shipped data file must be matched
by the package data of ``pyproject.toml``, or a wheel install silently loses the kernels (they fall back to
slow paths with a warning) and the shipped pipelines."""

from __future__ import annotations

import fnmatch
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    tomllib = pytest.importorskip("tomli")

REPO = Path(__file__).resolve().parents[1]
SHIPPED_SUFFIXES = (".cpp", ".h", ".yaml")


def _setuptools_config() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]


def _matched(relative: str, patterns: list[str]) -> bool:
    # setuptools globs package data relative to the package folder; "*" does not cross a "/".
    return any(
        fnmatch.fnmatch(relative, pattern) and relative.count("/") == pattern.count("/")
        for pattern in patterns
    )


def test_kernel_sources_and_pipelines_are_package_data():
    config = _setuptools_config()
    patterns = config["package-data"]["*"]
    folders = {package: REPO / folder for package, folder in config["package-dir"].items()}
    unmatched, seen = [], 0
    for package, folder in folders.items():
        nested = [REPO / f for p, f in config["package-dir"].items() if p.startswith(package + ".")]
        for path in folder.rglob("*"):
            if path.suffix not in SHIPPED_SUFFIXES or any(path.is_relative_to(n) for n in nested):
                continue
            seen += 1
            if not _matched(path.relative_to(folder).as_posix(), patterns):
                unmatched.append(str(path.relative_to(REPO)))
    assert seen >= 5, "expected the rasterizer and silhouette kernels and the pipelines among the files"
    assert not unmatched, f"not in [tool.setuptools.package-data]: {unmatched}"
