"""Statistics over subjects: means with bootstrap intervals, and paired comparisons that decide a win.

The unit of evidence is the subject: each subject's number is the mean over its images (lights ×
cameras), and a table's mean is the mean over its subjects. Intervals are percentile bootstrap intervals
of that mean, resampling subjects with replacement (:data:`RESAMPLES` resamples, seed :data:`SEED`, level
:data:`CONFIDENCE`), so the same numbers always give the same interval. A comparison of two methods on
the same subjects bootstraps the mean of the per-subject differences; it is a *win* only when that
interval lies entirely on the better side of 0. With fewer than :data:`MIN_SUBJECTS` subjects no interval
is given and nothing is a win.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

RESAMPLES = 10_000
SEED = 0
CONFIDENCE = 0.95
MIN_SUBJECTS = 2
# +1: larger is better (PSNR, SSIM); -1: smaller is better (RMSE, LPIPS). Space suffixes share the sign.
BETTER = {"psnr": 1, "ssim": 1, "rmse": -1, "lpips": -1}


def better_sign(metric: str) -> int:
    """+1 when larger values of ``metric`` (``psnr``, ``ssim_srgb``, ...) are better, -1 when smaller are."""
    return BETTER[metric.split("_", 1)[0]]


def bootstrap_interval(
    values: Sequence[float], resamples: int = RESAMPLES, seed: int = SEED, confidence: float = CONFIDENCE
) -> tuple[float, float] | None:
    """Percentile bootstrap interval of the mean of ``values`` (N,), resampling them with replacement;
    None for fewer than :data:`MIN_SUBJECTS` values."""
    data = np.asarray(values, dtype=np.float64)
    if data.size < MIN_SUBJECTS:
        return None
    rng = np.random.default_rng(seed)
    means = data[rng.integers(0, data.size, size=(resamples, data.size))].mean(axis=1)
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(means, [tail, 100 - tail])
    return float(low), float(high)


def mean_with_interval(values: Sequence[float]) -> dict:
    """{mean, low, high, subjects} of per-subject values (low/high None below two subjects)."""
    interval = bootstrap_interval(values)
    return {
        "mean": float(np.mean(values)),
        "low": None if interval is None else interval[0],
        "high": None if interval is None else interval[1],
        "subjects": len(values),
    }


def paired_comparison(metric: str, ours: Mapping[str, float], other: Mapping[str, float]) -> dict:
    """Method ``ours`` against ``other`` on their common subjects ({subject: value} each).

    Returns {mean, low, high, subjects} of the per-subject difference ours − other and ``win``: True
    when the interval excludes 0 on the better side of ``metric``, False otherwise."""
    common = sorted(set(ours) & set(other))
    differences = [ours[s] - other[s] for s in common]
    summary = mean_with_interval(differences) if common else {"mean": None, "low": None, "high": None}
    summary["subjects"] = len(common)
    sign = better_sign(metric)
    bounds = (summary["low"], summary["high"])
    summary["win"] = None not in bounds and min(b * sign for b in bounds) > 0
    return summary


def table_statistics(
    subjects: Mapping[str, Mapping[str, Mapping[str, float]]], pairs: Sequence[tuple[str, str]]
) -> dict:
    """Means with intervals and paired comparisons of one table.

    subjects: {subject: {row (method): {metric: the subject's mean value}}} (an ``images`` count is
    summed, not averaged). pairs: (ours, other) rows to compare. Returns {"mean": {row: {metric: mean,
    images: total}}, "interval": {row: {metric: {mean, low, high, subjects}}}, "comparisons": {"ours vs
    other": {metric: paired_comparison}}}.
    """
    per_row: dict[str, dict[str, dict[str, float]]] = {}
    for subject, rows in subjects.items():
        for row, metrics in rows.items():
            for metric, value in metrics.items():
                per_row.setdefault(row, {}).setdefault(metric, {})[subject] = value
    mean, interval = {}, {}
    for row, metrics in per_row.items():
        mean[row] = {
            m: int(np.sum(list(v.values()))) if m == "images" else float(np.mean(list(v.values())))
            for m, v in metrics.items()
        }
        interval[row] = {m: mean_with_interval(list(v.values())) for m, v in metrics.items() if m != "images"}
    comparisons = {}
    for ours, other in pairs:
        if ours in per_row and other in per_row:
            comparisons[f"{ours} vs {other}"] = {
                m: paired_comparison(m, per_row[ours][m], per_row[other][m])
                for m in per_row[ours]
                if m != "images" and m in per_row[other]
            }
    return {"mean": mean, "interval": interval, "comparisons": comparisons}
