"""The evaluation protocol: statistics over subjects, display-space metrics, LPIPS availability, the
protocol record and its hash, smoke vs reference runs, and the goals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relightanyone.evaluation import metrics, protocol, statistics
from relightanyone.evaluation.tables import EvaluationSettings
from relightanyone.model.fit.fitter import FitSettings


def test_bootstrap_interval_is_seeded_and_brackets_the_mean():
    values = [30.0, 31.5, 29.0, 33.0, 30.5]
    interval = statistics.bootstrap_interval(values)
    assert interval == statistics.bootstrap_interval(values)  # fixed seed: the same numbers
    assert interval[0] < np.mean(values) < interval[1]
    assert min(values) <= interval[0] and interval[1] <= max(values)
    assert statistics.bootstrap_interval([5.0, 5.0, 5.0]) == (5.0, 5.0)
    assert statistics.bootstrap_interval([5.0]) is None


def test_a_win_needs_the_paired_interval_to_exclude_zero():
    ours = {f"s{i}": 30.0 + i for i in range(5)}
    consistently_worse = {s: v - 0.5 - 0.1 * k for k, (s, v) in enumerate(ours.items())}
    mixed = {s: v + (1.0 if k % 2 else -1.2) for k, (s, v) in enumerate(ours.items())}
    assert statistics.paired_comparison("psnr", ours, consistently_worse)["win"] is True
    assert statistics.paired_comparison("psnr", ours, mixed)["win"] is False  # interval spans 0
    # RMSE: smaller is better, so ours being larger everywhere is no win.
    assert statistics.paired_comparison("rmse", ours, consistently_worse)["win"] is False
    assert statistics.paired_comparison("rmse_srgb", consistently_worse, ours)["win"] is True
    one = statistics.paired_comparison("psnr", {"a": 40.0}, {"a": 20.0})
    assert one["win"] is False and one["low"] is None and one["subjects"] == 1


def test_table_statistics_means_intervals_and_comparisons():
    subjects = {
        f"d1/s{i}": {"a": {"psnr": 30.0 + i, "images": 4}, "b": {"psnr": 28.0 + i, "images": 4}}
        for i in range(3)
    }
    summary = statistics.table_statistics(subjects, [("a", "b"), ("a", "missing")])
    assert summary["mean"]["a"] == {"psnr": 31.0, "images": 12}
    assert summary["interval"]["a"]["psnr"]["subjects"] == 3
    comparison = summary["comparisons"]["a vs b"]["psnr"]
    assert comparison["mean"] == pytest.approx(2.0) and comparison["low"] == pytest.approx(2.0)
    assert comparison["win"] is True and list(summary["comparisons"]) == ["a vs b"]


def test_srgb_metrics_weigh_dark_errors_as_a_viewer_sees_them():
    target = torch.full((1, 3, 16, 16), 0.02)
    prediction = target * 1.5  # 50 % too bright in the shadows
    mask = torch.ones(1, 1, 16, 16)
    scores = metrics.image_metrics(prediction, target, mask)
    assert set(scores) == {
        "psnr",
        "rmse",
        "ssim",
        "psnr_srgb",
        "rmse_srgb",
        "ssim_srgb",
        "psnr_level_aligned",
    }
    assert scores["psnr"].item() > 38 and scores["psnr_srgb"].item() < scores["psnr"].item() - 10
    same = metrics.image_metrics(target, target, mask)
    assert same["psnr_srgb"].item() == pytest.approx(120.0)


def test_level_aligned_psnr_removes_a_global_level_and_nothing_else():
    rng = torch.Generator().manual_seed(0)
    target = torch.rand(2, 3, 16, 16, generator=rng) * 0.5
    mask = torch.ones(2, 1, 16, 16)
    mask[:, :, :4] = 0  # outside the mask nothing counts
    dimmer = target * torch.tensor([0.6, 1.3]).view(2, 1, 1, 1)
    dimmer[:, :, :4] = 1.0
    assert metrics.level_aligned_psnr(dimmer, target, mask).tolist() == pytest.approx([120.0, 120.0], abs=0.5)
    assert metrics.image_metrics(dimmer, target, mask)["psnr"].max().item() < 30
    # A change of colour (not of level) stays an error.
    tinted = target * torch.tensor([1.3, 1.0, 0.7]).view(1, 3, 1, 1)
    assert metrics.level_aligned_psnr(tinted, target, mask).max().item() < 40


def test_lpips_is_skipped_without_cached_backbone_weights(tmp_path, monkeypatch):
    available, reason = metrics.lpips_status(tmp_path)
    assert not available and reason.startswith("skipped:")  # nothing here is downloaded
    monkeypatch.setattr(metrics, "lpips_import_problem", lambda: None)
    assert metrics.lpips_status(tmp_path) == (False, "skipped: backbone weights not available offline")
    (tmp_path / "alexnet-owt-7be5be79.pth").write_bytes(b"")
    assert metrics.lpips_status(tmp_path)[0] is True


def test_protocol_hash_changes_with_any_setting_but_not_with_progress():
    record = protocol.protocol_record(EvaluationSettings(), FitSettings())
    quiet = protocol.protocol_record(EvaluationSettings(progress=False), FitSettings(progress=False))
    assert protocol.protocol_hash(record) == protocol.protocol_hash(quiet)
    for settings, fit in (
        (EvaluationSettings(split="val"), FitSettings()),
        (EvaluationSettings(), FitSettings(lighting_prior_weight=0.5)),
        (EvaluationSettings(max_views=4), FitSettings()),
    ):
        assert protocol.protocol_hash(protocol.protocol_record(settings, fit)) != protocol.protocol_hash(
            record
        )
    assert record["statistics"]["resamples"] == 10_000 and record["split"] == "test"


def _results(subjects_per_dataset: int, two_stage: float, single_stage: float) -> dict:
    table1 = {
        f"d1/s{i}": {
            "source": "rows",
            "cameras": ["c0"],
            "metrics": {"two_stage": {"psnr": two_stage + 0.1 * i}, "single_stage": {"psnr": single_stage}},
        }
        for i in range(subjects_per_dataset)
    }
    table3b = {
        f"d2/f{i}": {"source": "rows", "cameras": ["c0"], "metrics": {"two_stage": {"psnr": 25.0}}}
        for i in range(subjects_per_dataset)
    }
    results = {
        "table1": {"subjects": table1, "mean": {"two_stage": {"psnr": two_stage}}},
        "table3_fitted": {"subjects": table3b, "mean": {}},
        "table3": {
            "subjects": {
                f"{d}/t0": {
                    "source": "rows",
                    "cameras": ["c0"],
                    "metrics": {"with_lighting_code": {"psnr": v}},
                }
                for d, v in (("d2", 29.0), ("d3", 27.0))
            },
            "mean": {},
        },
    }
    protocol.add_statistics(results)
    return results


def test_smoke_and_reference_runs_and_the_goals():
    smoke = _results(2, 31.0, 29.0)
    assert protocol.run_kind(smoke) == "smoke run" and protocol.held_out_counts(smoke) == {"d1": 2, "d2": 2}
    reference = _results(5, 31.0, 29.0)
    assert protocol.run_kind(reference) == "reference evaluation"
    checked = protocol.goals(reference)
    values = list(checked.values())
    assert values[0] is True and values[1] is True  # >= 30 dB, and an interval win over single-stage
    assert values[2] is None  # no Table 2: not evaluated
    expansion = next(k for k in checked if k.startswith("Table 3: expansion"))
    assert checked[expansion] is False and "d2 29.00, d3 27.00" in expansion  # d3 under 28 dB
    assert protocol.goals(_results(5, 29.0, 29.5))[next(iter(checked))] is False
    stage1 = next(k for k in checked if k.startswith("Stage 1"))
    assert checked[stage1] is None  # no stage-1 metrics recorded
    reference["stage1_held_out"] = {"faceolat": {"psnr": 42.2}, "nersemble": {"psnr": 23.9}}
    assert list(protocol.goals(reference).values())[-1] is False
    reference["stage1_held_out"]["nersemble"]["psnr"] = 28.5
    assert list(protocol.goals(reference).values())[-1] is True


def test_the_report_shows_intervals_wins_and_the_run_kind(tmp_path):
    from relightanyone.evaluation.report import write_report

    results = _results(5, 31.0, 29.0)
    results["run_kind"] = protocol.run_kind(results)
    report = write_report(tmp_path, results, {}, {}).read_text()
    assert report.startswith("# Evaluation on the synthetic world (reference evaluation)")
    assert "ΔPSNR +2.20 dB, [+2.08, +2.32] dB: **win**" in report
    assert "| two-stage, paper \\(different data, not comparable\\) | 30.06 |" in report
    smoke = _results(1, 31.0, 29.0)
    report = write_report(tmp_path, smoke, {}, {}).read_text()
    assert "(smoke run)" in report and "no interval (1 subject), not a win" in report


def test_the_lighting_prior_of_evaluate_defaults_to_the_fit_default():
    from relightanyone.evaluation.cli import evaluate_command

    option = next(p for p in evaluate_command.params if p.name == "lighting_prior_weight")
    assert option.default == EvaluationSettings().lighting_prior_weight == FitSettings().lighting_prior_weight
