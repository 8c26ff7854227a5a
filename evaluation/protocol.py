"""The evaluation protocol as data: what is compared, the goals, the paper's numbers, and a hash.

The protocol record (:func:`protocol_record`) holds every setting that decides a number: the split, the
fit's budget and prior (:class:`~relightanyone.model.fit.fitter.FitSettings`), the evaluation limits, the
metric definitions and the statistics. ``evaluation.json`` stores it with its SHA-256
(:func:`protocol_hash`), so two evaluations are comparable exactly when their hashes agree, and a
setting changed after the test numbers were seen shows as another hash. ``docs/evaluation.md`` states
the same protocol in words.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import Any

from relightanyone.evaluation import statistics
from relightanyone.evaluation.metrics import LEVEL_ALIGNED, LINEAR_METRICS, SRGB_SUFFIX
from relightanyone.hashing import sha256_bytes

PROTOCOL_VERSION = 1
# Fewer held-out subjects than this in any evaluated dataset makes the run a smoke run: its intervals
# and wins are computed the same way but say little.
REFERENCE_MIN_SUBJECTS = 5
SMOKE_RUN = "smoke run"
REFERENCE_RUN = "reference evaluation"
# (ours, other) rows compared with paired intervals in each table.
COMPARISONS = {
    "table1": [("two_stage", "single_stage")],
    "table2": [("multi_view", "single_image")],
    "table3": [("with_lighting_code", "without_lighting_code"), ("with_lighting_code", "colour_matrix")],
    "table3_fitted": [
        ("with_lighting_code", "without_lighting_code"),
        ("with_lighting_code", "colour_matrix"),
    ],
}
# The metric whose paired interval decides a win (the goals below).
DECIDING_METRIC = "psnr"
HELD_OUT_TABLES = ("table1", "table2", "table3_fitted")
# The paper's published numbers (RelightAnyone, Tables 1 and 2), on its own real captures: another
# dataset, resolution and protocol than this synthetic world, so they are shown beside ours, never
# compared with them.
PAPER_NOTE = "paper (different data, not comparable)"
PAPER_NUMBERS = {
    "table1": {
        "two-stage, " + PAPER_NOTE: {"psnr": 30.06, "rmse": 0.0655, "ssim": 0.87},
        "single-stage, " + PAPER_NOTE: {"psnr": 25.49, "ssim": 0.76},
    },
    "table2": {
        "multi-view, " + PAPER_NOTE: {"psnr": 29.07},
        "single image, " + PAPER_NOTE: {"psnr": 26.57},
    },
}
# Goals on the test split (mean PSNR over test subjects, linear RGB, in dB).
TABLE1_TWO_STAGE_PSNR = 30.0
TABLE2_MULTI_VIEW_PSNR = 27.0
TABLE2_SINGLE_IMAGE_PSNR = 24.0
EXPANSION_PSNR = 28.0  # Table 3, with z_l, on each flat-lit dataset
STAGE1_HELD_OUT_PSNR = 28.0  # stage 1's held-out cameras of its training subjects, on every dataset


def protocol_record(settings: Any, fit_settings: Any) -> dict:
    """Every setting that decides an evaluation's numbers, JSON-ready.

    settings: the :class:`~relightanyone.evaluation.tables.EvaluationSettings`; fit_settings: the
    :class:`~relightanyone.model.fit.fitter.FitSettings` of every fit. Progress flags are left out.
    """
    without_progress = lambda record: {k: v for k, v in asdict(record).items() if k != "progress"}  # noqa: E731
    return {
        "version": PROTOCOL_VERSION,
        "split": settings.split,
        "evaluation": without_progress(settings),
        "fit": without_progress(fit_settings),
        "metrics": {
            "linear": list(LINEAR_METRICS),
            "srgb": [f"{m}{SRGB_SUFFIX}" for m in LINEAR_METRICS],
            "diagnostic": [LEVEL_ALIGNED],
            "range": "both images clipped to [0, 1] (linear RGB); sRGB = the display encoding of that",
            "mask": "the answer's subject mask eroded by 1 px, limited to the row mask; SSIM over mask > 0.5",
            "psnr_peak": 1.0,
            "lpips": "AlexNet through torchvision (torchmetrics), sRGB, only with cached weights",
            "per_subject": "mean over the subject's images (lights x cameras)",
            "stage1_held_out": "stage 1's run: every held-out view of its training subjects, PSNR over the row "
            "mask's interior (its 1-px edge ring dropped), mean over a dataset's views; psnr_row_mask beside it",
        },
        "statistics": {
            "unit": "subject",
            "interval": "percentile bootstrap of the mean over subjects",
            "resamples": statistics.RESAMPLES,
            "seed": statistics.SEED,
            "confidence": statistics.CONFIDENCE,
            "min_subjects": statistics.MIN_SUBJECTS,
            "win": f"the interval of the paired {DECIDING_METRIC} difference excludes 0",
            "comparisons": {table: [list(pair) for pair in pairs] for table, pairs in COMPARISONS.items()},
        },
        "goals_db": {
            "table1_two_stage": TABLE1_TWO_STAGE_PSNR,
            "table2_multi_view": TABLE2_MULTI_VIEW_PSNR,
            "table2_single_image": TABLE2_SINGLE_IMAGE_PSNR,
            "expansion_per_flat_dataset": EXPANSION_PSNR,
            "stage1_held_out_views_per_dataset": STAGE1_HELD_OUT_PSNR,
        },
    }


def protocol_hash(record: dict) -> str:
    """SHA-256 of the record's canonical JSON (sorted keys, no spaces; paths and other values as text)."""
    return sha256_bytes(json.dumps(record, sort_keys=True, separators=(",", ":"), default=str).encode())


def add_statistics(results: dict) -> None:
    """Add ``interval`` and ``comparisons`` (:func:`statistics.table_statistics`, pairs from
    :data:`COMPARISONS`) to every table of ``results`` (an entry with per-subject ``subjects``)."""
    for table, entry in results.items():
        if (
            not isinstance(entry, dict)
            or not isinstance(entry.get("subjects"), dict)
            or not entry["subjects"]
        ):
            continue
        per_subject = {key: subject["metrics"] for key, subject in entry["subjects"].items()}
        summary = statistics.table_statistics(per_subject, COMPARISONS.get(table, []))
        entry["interval"] = summary["interval"]
        entry["comparisons"] = summary["comparisons"]


def held_out_counts(results: dict) -> dict[str, int]:
    """Held-out subjects scored per world dataset (d1..d4), over the held-out tables."""
    subjects: dict[str, set[str]] = {}
    for table in HELD_OUT_TABLES:
        for key in results.get(table, {}).get("subjects", {}):
            dataset = key.split("/", 1)[0]
            subjects.setdefault(dataset, set()).add(key)
    return {dataset: len(keys) for dataset, keys in sorted(subjects.items())}


def run_kind(results: dict) -> str:
    """:data:`REFERENCE_RUN` when every evaluated dataset has :data:`REFERENCE_MIN_SUBJECTS` held-out
    subjects, else :data:`SMOKE_RUN`."""
    counts = held_out_counts(results)
    enough = counts and min(counts.values()) >= REFERENCE_MIN_SUBJECTS
    return REFERENCE_RUN if enough else SMOKE_RUN


def _mean(results: dict, table: str, row: str) -> float | None:
    return results.get(table, {}).get("mean", {}).get(row, {}).get(DECIDING_METRIC)


def _at_least(value: float | None, goal: float) -> bool | None:
    return None if value is None else value >= goal


def _win(results: dict, table: str, ours: str, other: str) -> bool | None:
    comparison = results.get(table, {}).get("comparisons", {}).get(f"{ours} vs {other}")
    return None if comparison is None else bool(comparison[DECIDING_METRIC]["win"])


def expansion_by_dataset(results: dict) -> dict[str, float]:
    """Table 3 (with z_l) mean PSNR per flat-lit world dataset."""
    values: dict[str, list[float]] = {}
    for key, subject in results.get("table3", {}).get("subjects", {}).items():
        value = subject["metrics"].get("with_lighting_code", {}).get(DECIDING_METRIC)
        if value is not None:
            values.setdefault(key.split("/", 1)[0], []).append(value)
    return {dataset: sum(v) / len(v) for dataset, v in sorted(values.items())}


def goals(results: dict) -> dict[str, bool | None]:
    """The evaluation's goals (None: not evaluated). A comparison counts only as an interval win."""
    expansion = expansion_by_dataset(results)
    held_out = {name: v["psnr"] for name, v in (results.get("stage1_held_out") or {}).items()}
    return {
        f"Table 1: two-stage mean PSNR >= {TABLE1_TWO_STAGE_PSNR:g} dB": _at_least(
            _mean(results, "table1", "two_stage"), TABLE1_TWO_STAGE_PSNR
        ),
        "Table 1: two-stage beats single-stage (95 % interval of the paired PSNR difference excludes 0)": _win(
            results, "table1", "two_stage", "single_stage"
        ),
        f"Table 2: multi-view mean PSNR >= {TABLE2_MULTI_VIEW_PSNR:g} dB": _at_least(
            _mean(results, "table2", "multi_view"), TABLE2_MULTI_VIEW_PSNR
        ),
        f"Table 2: single-image mean PSNR >= {TABLE2_SINGLE_IMAGE_PSNR:g} dB": _at_least(
            _mean(results, "table2", "single_image"), TABLE2_SINGLE_IMAGE_PSNR
        ),
        f"Table 3: expansion PSNR >= {EXPANSION_PSNR:g} dB on every flat-lit dataset "
        f"({', '.join(f'{d} {v:.2f}' for d, v in expansion.items()) or 'none'})": (
            all(v >= EXPANSION_PSNR for v in expansion.values()) if expansion else None
        ),
        "Table 3: training with z_l beats training without it (PSNR interval)": _win(
            results, "table3", "with_lighting_code", "without_lighting_code"
        ),
        "Table 3: training with z_l beats the 3x3 colour-matrix baseline (PSNR interval)": _win(
            results, "table3", "with_lighting_code", "colour_matrix"
        ),
        f"Stage 1: held-out-view PSNR >= {STAGE1_HELD_OUT_PSNR:g} dB on every dataset "
        f"({', '.join(f'{d} {v:.2f}' for d, v in held_out.items()) or 'not recorded'})": (
            all(v >= STAGE1_HELD_OUT_PSNR for v in held_out.values()) if held_out else None
        ),
    }
