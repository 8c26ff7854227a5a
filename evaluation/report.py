"""The evaluation's outputs: ``evaluation.json``, ``report.md`` and image grids (``grids/*.png``).

Grids show, per lighting (one row each): the fit's input image | ground truth | each method | each
method's error map. Images are sRGB-encoded after one exposure per row (the truth's 99th percentile
inside the mask maps to 0.9); error maps show the mean absolute channel error with the inferno colour map,
full scale at ``ERROR_FULL_SCALE`` of that row's exposure.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from urllib.parse import quote

import numpy as np

from relightanyone.align.colour import linear_to_display
from relightanyone.evaluation.ablation import budget_text
from relightanyone.evaluation.protocol import (
    DECIDING_METRIC,
    PAPER_NUMBERS,
    REFERENCE_MIN_SUBJECTS,
    SMOKE_RUN,
    goals,
)
from relightanyone.evaluation.statistics import CONFIDENCE, RESAMPLES

ERROR_FULL_SCALE = 0.25
MIN_TILE = 128
GRID_ROWS = 3
METRIC_ORDER = ("psnr", "ssim", "rmse", "psnr_srgb", "ssim_srgb", "rmse_srgb", "psnr_level_aligned", "lpips")
ARROWS = {
    "psnr": "PSNR ↑",
    "ssim": "SSIM ↑",
    "rmse": "RMSE ↓",
    "psnr_srgb": "sRGB PSNR ↑",
    "ssim_srgb": "sRGB SSIM ↑",
    "rmse_srgb": "sRGB RMSE ↓",
    "psnr_level_aligned": "level-aligned PSNR ↑ (diagnostic)",
    "lpips": "LPIPS ↓",
}
ROW_NAMES = {
    "two_stage": "two-stage (ours)",
    "single_stage": "single-stage baseline",
    "multi_view": "ours, multi-view fit",
    "single_image": "ours, single-image fit",
    "with_lighting_code": "with z_l (trained with lighting codes: the method)",
    "without_lighting_code": "without z_l (stage 1 trained without lighting codes)",
    "colour_matrix": "3×3 colour matrix per dataset, no z_l",
}
# Characters that start Markdown syntax (emphasis, links, images, code, table cells) anywhere in a line.
MARKDOWN_SPECIAL = re.compile(r"([\\`*_\[\]()!|])")


def markdown_text(value: object) -> str:
    """``value`` as literal Markdown text: names and paths come from datasets and the command line, so
    Markdown syntax in them is backslash-escaped and ``& < >`` become entities (no HTML, no links, no
    broken table cells); a line break becomes a space."""
    text = " ".join(str(value).splitlines())
    text = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return MARKDOWN_SPECIAL.sub(r"\\\1", text)


def markdown_code(value: object) -> str:
    """``value`` as a Markdown code span, fenced with more backticks than any run inside it."""
    text = " ".join(str(value).splitlines())
    fence = "`" * (max((len(run) for run in re.findall(r"`+", text)), default=0) + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def error_map(prediction: np.ndarray, truth: np.ndarray, mask: np.ndarray, exposure: float) -> np.ndarray:
    """Mean absolute error (H, W) -> inferno-coloured uint8 (H, W, 3) RGB, zero outside the mask."""
    import cv2

    error = np.abs(prediction - truth).mean(axis=-1) * exposure / ERROR_FULL_SCALE
    scaled = (np.clip(error, 0, 1) * 255).astype(np.uint8)
    coloured = cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)[..., ::-1]
    return np.where(mask[..., None] > 0.5, coloured, 0).astype(np.uint8)


def _tile(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    if image.shape[:2] != size:
        image = cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)
    return image


def _label(text: str, width: int) -> np.ndarray:
    import cv2

    strip = np.full((18, width, 3), 255, np.uint8)
    cv2.putText(
        strip, text[: max(4, width // 7)], (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 1, cv2.LINE_AA
    )
    return strip


def save_grid(
    path: Path, input_image: np.ndarray | None, rows: dict[str, list], limit: int = GRID_ROWS
) -> Path:
    """One PNG: per case (up to ``limit``): input | truth | methods... | error maps...

    rows: method name -> that method's Comparison.examples (label, prediction (3, H, W), truth, mask).
    """
    from PIL import Image

    methods = list(rows)
    first = rows[methods[0]]
    height, width = first[0][2].shape[1:]
    scale = max(1, int(np.ceil(MIN_TILE / max(height, 1))))
    size = (height * scale, width * scale)
    header = ["input"] * (input_image is not None) + ["truth"] + methods + [f"error {m}" for m in methods]
    lines = [np.concatenate([_label(h, size[1]) for h in header], axis=1)]
    for index, (label, _, truth, mask) in enumerate(first[:limit]):
        truth_hwc = truth.transpose(1, 2, 0)
        inside = truth_hwc[mask > 0.5]
        exposure = 0.9 / max(float(np.percentile(inside, 99)) if inside.size else 1.0, 1e-6)
        tiles = []
        if input_image is not None:
            shown = input_image * (0.9 / max(float(np.percentile(input_image, 99)), 1e-6))
            tiles.append(_tile(linear_to_display(shown, 1.0), size))
        tiles.append(_tile(linear_to_display(truth_hwc, exposure), size))
        predictions = [rows[m][index][1].transpose(1, 2, 0) for m in methods]
        tiles += [_tile(linear_to_display(p, exposure), size) for p in predictions]
        tiles += [_tile(error_map(p, truth_hwc, mask, exposure), size) for p in predictions]
        lines.append(np.concatenate([_label(label, size[1] * len(tiles))], axis=1))
        lines.append(np.concatenate(tiles, axis=1))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(lines, axis=0)).save(path)
    return path


def _format(metric: str, value: float | None) -> str:
    if value is None:
        return "–"
    return f"{value:.2f}" if metric.startswith("psnr") else f"{value:.4f}"


def metric_table(
    rows: dict[str, dict],
    metrics: list[str],
    extra: dict[str, dict] | None = None,
    budgets: dict[str, dict] | None = None,
) -> list[str]:
    """Markdown table lines: one line per method (results rows then extra rows such as paper numbers),
    with each method's training budget when ``budgets`` (row -> budget) is given."""
    budget_column = budgets is not None
    lines = [
        "| method | "
        + " | ".join(ARROWS[m] for m in metrics)
        + " | images |"
        + (" training budget |" if budget_column else "")
    ]
    lines.append("|---" * (len(metrics) + 2 + budget_column) + "|")
    for name, values in rows.items():
        cells = " | ".join(_format(m, values.get(m)) for m in metrics)
        budget = f" {markdown_text(budget_text(budgets.get(name)))} |" if budget_column else ""
        lines.append(
            f"| {markdown_text(ROW_NAMES.get(name, name))} | {cells} | {values.get('images', '–')} |{budget}"
        )
    for name, values in (extra or {}).items():
        # Published numbers exactly as printed (0.87, not 0.8700).
        cells = " | ".join(f"{values[m]:g}" if m in values else "–" for m in metrics)
        lines.append(f"| {markdown_text(name)} | {cells} | – |" + (" – |" if budget_column else ""))
    return lines


def interval_lines(entry: dict) -> list[str]:
    """The table's mean PSNR per method with its bootstrap interval, and each paired comparison."""
    lines = []
    for row, metrics in entry.get("interval", {}).items():
        value = metrics.get(DECIDING_METRIC)
        if value is None:
            continue
        bounds = f"[{value['low']:.2f}, {value['high']:.2f}]" if value["low"] is not None else "no interval"
        lines.append(
            f"- {markdown_text(ROW_NAMES.get(row, row))}: PSNR {value['mean']:.2f} dB {bounds} "
            f"({value['subjects']} subjects)"
        )
    for name, metrics in entry.get("comparisons", {}).items():
        value = metrics.get(DECIDING_METRIC)
        if value is None or value["mean"] is None:
            continue
        ours, other = (ROW_NAMES.get(row, row) for row in name.split(" vs "))
        if value["low"] is None:
            verdict = f"no interval ({value['subjects']} subject), not a win"
        else:
            verdict = f"[{value['low']:+.2f}, {value['high']:+.2f}] dB: " + (
                "**win**" if value["win"] else "not a win (the interval includes 0 or favours the other)"
            )
        lines.append(
            f"- {markdown_text(ours)} − {markdown_text(other)}: ΔPSNR {value['mean']:+.2f} dB, {verdict}"
        )
    if lines:
        lines = [
            f"Means over subjects with {CONFIDENCE:.0%} percentile bootstrap intervals ({RESAMPLES:,} "
            "resamples of the subjects); a difference is a win only when its interval excludes 0:",
            "",
            *lines,
            "",
        ]
    return lines


def write_json(path: Path, results: dict) -> Path:
    """Atomic JSON write (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(results, indent=1, sort_keys=True))
    os.replace(temporary, path)
    return path


def write_grids(out: Path, tables: dict, input_images: dict[str, np.ndarray]) -> dict[str, list[str]]:
    """grids/<table>_<dataset>_<subject>.png for every evaluated subject -> table -> relative paths."""
    written: dict[str, list[str]] = {}
    for table, entries in tables.items():
        for key, entry in entries.items():
            rows = {name: comparison.examples for name, comparison in entry["rows"].items()}
            name = f"grids/{table}_{key.replace('/', '_')}.png"
            save_grid(out / name, input_images.get(key), rows)
            written.setdefault(table, []).append(name)
    return written


TABLE_TEXT = {
    "table1": (
        "Table 1 analogue: OLAT relighting of held-out OLAT-dataset subjects",
        "Each subject is fitted on its full-on frame (multi-view) and relit under single rig lights; "
        "compared with its OLAT images. Two-stage = stage 1 + stage 2; single-stage = the baseline "
        "trained on the OLAT dataset alone, fitted with the same settings.",
    ),
    "table2": (
        "Table 2 analogue: environment-map relighting, single image vs multi-view fitting",
        "The truth is the world's image-based relighting of its true OLAT images with each environment "
        "map; the model's OLAT renders are combined with the same per-light weights (recovered from the "
        "answers by least squares). The single-image fit uses the most frontal camera only; both fits are "
        "compared in all evaluation cameras.",
    ),
    "table3": (
        "Table 3: the lighting-code ablation on flat-lit subjects (expansion accuracy)",
        "Each arm is a stage 1 and its stage 2 trained on the same data: *with z_l* (the method), *without "
        "z_l* (stage 1 trained without lighting codes) and the *3×3 colour matrix* baseline (no lighting "
        "codes; every flat-lit dataset aligned to the OLAT dataset by a learned 3×3 matrix before stage 1). "
        "Stage-1 training subjects of the flat-lit datasets (never seen lit by single lights; stage 2 never "
        "saw them) are decoded from their identity codes without fitting, as the OLAT expansion renders "
        "them, relit under rig lights and compared with their true OLAT images (rendered from the world).",
    ),
    "table3_fitted": (
        "Table 3b: held-out flat-lit subjects, fitted",
        "Held-out subjects of the flat-lit datasets, fitted on their full-on frame (multi-view), relit "
        "under rig lights and compared with their true OLAT images; with every ablation arm when the "
        "evaluation fits them all, else with the main two-stage runs. Fitting also estimates the scene "
        "lighting and finetunes stage 1, which can absorb part of what the arms change.",
    ),
}
TABLES = ("table1", "table2", "table3", "table3_fitted")
ABLATION_TABLES = ("table3", "table3_fitted")


def ablation_note(ablation: dict) -> str:
    """One line on the ablation's arms: whether they were trained on equal budgets."""
    arms = ", ".join(markdown_text(ROW_NAMES.get(row, row)) for row in ablation.get("arms", {}))
    if ablation.get("budgets_agree"):
        return f"Arms: {arms}; every arm trained the same number of views in stage 1 and in stage 2."
    return (
        f"Arms: {arms}. **The arms' training budgets differ** (column above), so the comparison is not "
        "at equal budget."
    )


# Tables whose subjects are stage-1 training subjects on purpose (no held-out warning there).
TRAINING_SUBJECT_TABLES = ("table3",)


def write_report(out: Path, results: dict, tables: dict, input_images: dict[str, np.ndarray]) -> Path:
    """report.md (tables, goals, grids) and evaluation.json in ``out``; returns the report path."""
    out = Path(out)
    grids = write_grids(out, tables, input_images)
    metrics = [
        m
        for m in METRIC_ORDER
        if any(m in row for t in TABLES for row in results.get(t, {}).get("mean", {}).values())
    ]
    checked = goals(results)
    results["goals"] = dict(checked)
    results["grids"] = grids
    kind = results.get("run_kind", SMOKE_RUN)
    counts = results.get("held_out_subjects", {})
    settings = results.get("settings", {})
    inputs = results.get("inputs", {})
    datasets = ", ".join(
        f"{markdown_code(k)} = {markdown_code(v)}" for k, v in inputs.get("datasets", {}).items()
    )
    lines = [
        f"# Evaluation on the synthetic world ({kind})",
        "",
        "All numbers below are measured on a **synthetic world** (procedural heads, ray-traced), not on the "
        "paper's FaceOLAT / 3DPR captures; the paper's published numbers are shown beside them, labelled "
        "as different data and not comparable.",
        "",
    ]
    if kind == SMOKE_RUN:
        lines += [
            f"**Smoke run**: held-out subjects per dataset {markdown_text(counts or 'none')}, fewer than the "
            f"{REFERENCE_MIN_SUBJECTS} of a reference evaluation, so intervals and wins say little.",
            "",
        ]
    lines += [
        "## Setup",
        "",
        f"- split: {markdown_text(settings.get('split', 'test'))}; protocol SHA-256 "
        f"{markdown_code(results.get('protocol_sha256', 'not recorded'))} (settings in evaluation.json)",
        f"- world: {markdown_code(inputs.get('world'))}",
        "- training seeds: "
        + (
            ", ".join(f"{markdown_text(r['label'])} {r['seed']}" for r in results.get("training_runs", []))
            or "not recorded"
        )
        + " (one training seed per run: the retraining noise is not measured)",
        f"- datasets: {datasets}",
        f"- runs: stage 1 {markdown_code(inputs.get('stage1'))}, stage 2 {markdown_code(inputs.get('stage2'))}, "
        f"single-stage {markdown_code(inputs.get('single_stage') or 'not given')}",
        f"- fit budget: {settings.get('inversion_iterations')} inversion + {settings.get('finetune_iterations')} "
        f"finetuning iterations, {settings.get('views_per_step')} views per step",
        f"- limits: max views {settings.get('max_views')}, lights {len(results.get('light_indices', []))} "
        f"(rig indices {results.get('light_indices')}), environment maps {settings.get('envmaps') or 'all'}, "
        f"subjects per dataset {settings.get('subjects_per_dataset') or 'all'}",
        "- metrics: linear RGB clipped to [0, 1] and its sRGB display encoding (sRGB columns), inside the "
        "subject's mask; PSNR with peak 1, RMSE, SSIM (kornia, 11×11 Gaussian window, averaged over the "
        "mask); each metric is computed per image, averaged per subject, then over subjects, so mean PSNR "
        "is not the PSNR of the mean RMSE.",
        "- fit inputs of Tables 1-2: "
        + (
            "the world's renders under a lighting unknown to the fit (per subject: `input` in evaluation.json); "
            "the lighting prior is the OLAT dataset's full-on rig"
            if settings.get("unknown_lighting")
            else "the dataset's full-on rows (lit by the calibrated rig the lighting prior starts from)"
        ),
        "- single image (Table 2): "
        + (
            "a monocular-quality mesh, a mask from the image alone and a generic focal length"
            if settings.get("monocular_single_image")
            else "the dataset's tracked mesh, mask and calibration"
        ),
        f"- {results.get('lpips')}",
        f"- light units: {results.get('units', {}).get('note', 'not checked (no OLAT rows with answers)')}"
        + (
            f" (rows / answers = {results['units']['rows_over_answers']})"
            if "rows_over_answers" in results.get("units", {})
            else ""
        ),
    ]
    olat_ratio = results.get("units", {}).get("olat_sum_over_full_on")
    expected = results.get("units", {}).get("expected_from_lights", 1.0)
    if olat_ratio is not None:
        lines.append(
            f"- OLAT dataset: Σ OLAT frames / full-on frame = {olat_ratio:.2f}; the rig's recorded OLAT and "
            f"full-on intensities predict {expected:.2f}: "
            + (
                "consistent (training and fitting use each pattern's own intensities)."
                if abs(olat_ratio / expected - 1) < 0.25
                else "**the full-on and OLAT frames are in different units**, so a subject fitted on a "
                "full-on frame is relit in the full-on unit and Table 1 compares it with OLAT frames in another."
            )
        )
    lines.append("")
    for table in TABLES:
        title, text = TABLE_TEXT[table]
        lines += [f"## {title}", "", text, ""]
        entry = results.get(table, {})
        if not entry.get("subjects"):
            lines += ["Not evaluated (no subject with this kind of truth).", ""]
            continue
        extra = PAPER_NUMBERS.get(table, {})
        lines += (
            ["Mean over subjects (images: total):", ""]
            + metric_table(entry["mean"], metrics, extra, entry.get("budgets"))
            + [""]
        )
        if table in ABLATION_TABLES and "ablation" in results:
            lines += [ablation_note(results["ablation"]), ""]
        lines += interval_lines(entry)
        for key, subject in entry["subjects"].items():
            cameras = ", ".join(markdown_text(c) for c in subject["cameras"])
            lines += [
                f"**{markdown_text(key)}** — truth: {markdown_text(subject['source'])}; cameras: {cameras}",
                "",
            ]
            if subject.get("seen_in_training") and table not in TRAINING_SUBJECT_TABLES:
                runs = ", ".join(markdown_text(r) for r in subject["seen_in_training"])
                lines += [
                    f"> **Not held out:** {markdown_text(key)} is a training subject of the {runs} "
                    "run(s), so these numbers overstate generalization.",
                    "",
                ]
            lines += metric_table(subject["metrics"], metrics) + [""]
        for name in grids.get(table, []):
            lines += [f"![{markdown_text(name)}]({quote(name)})", ""]
    lines += ["## Goals", ""]
    for claim, value in checked.items():
        verdict = "not evaluated" if value is None else ("yes" if value else "**no**")
        lines.append(f"- {claim}: {verdict}")
    lines += ["", "## Fit times (s)", ""]
    lines += [f"- {k}: {v}" for k, v in results.get("timings_s", {}).items()]
    lines.append("")
    write_json(out / "evaluation.json", results)
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report
