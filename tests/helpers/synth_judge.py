"""Reading the synthetic world's answers in tests: the judge side of the ingest checks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from relightanyone.synth.truth import DatasetTruth


def truth_of(world: Path, dataset: str) -> DatasetTruth:
    return DatasetTruth.load(world / "answers" / dataset / "truth.json")


def subject_vertices(world: Path, dataset: str, subject: str) -> np.ndarray:
    """(V, 3) canonical vertices of a subject's true shape (answers/<d>/subjects/<s>/shape.obj)."""
    lines = (world / "answers" / dataset / "subjects" / subject / "shape.obj").read_text().splitlines()
    return np.array([[float(v) for v in line.split()[1:4]] for line in lines if line.startswith("v ")])


def project(K: np.ndarray, w2c: np.ndarray, dist: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) OpenCV projection of (N, 3) world points."""
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(w2c[:3, :3]))
    pixels, _ = cv2.projectPoints(
        points.reshape(-1, 1, 3), rvec, w2c[:3, 3].copy(), K, np.asarray(dist, dtype=np.float64)
    )
    return pixels.reshape(-1, 2)
