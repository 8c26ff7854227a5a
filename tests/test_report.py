"""The HTML report: sections from tiny inputs, "not produced" notes, determinism, and a headless Chromium
check that every picture of the page decodes (and that the check notices one that does not)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers.sphere_world import (
    LIGHTS,
    lambert_sphere,
    rig_lights,
    sphere_camera,
    sphere_row,
    write_flat_world,
    write_olat_world,
)
from PIL import Image

from relightanyone.format.schema import (
    DatasetInfo,
    Provenance,
    fingerprint_config,
)
from relightanyone.format.shards import ShardWriter
from relightanyone.pipelines.report.browser import BrowserUnavailable, check_in_browser, find_chromium
from relightanyone.pipelines.report.build import ReportInputs, ReportWarning, build_report
from relightanyone.pipelines.report.command import report_command
from relightanyone.pipelines.report.html import markdown_to_html, rewrite_links
from relightanyone.pipelines.report.metrics import metrics_tables

SECTIONS = ["datasets", "pictures", "lighting", "expanded", "relighting", "evaluation", "metrics"]
# Light k of the expanded world has intensity EXPANDED_INTENSITY[k]: light 3 is dimmest.
EXPANDED_INTENSITY = [4.0, 2.0, 1.0, 0.25]

EVALUATION_MD = """# Relighting evaluation

Held-out subjects under the answer lights.

| method | PSNR | SSIM |
|---|---|---|
| two-stage | 31.2 | 0.912 |
| single-stage | 27.9 | 0.871 |

![error grid](grids/errors.png)

- linear RGB, masked
"""


@pytest.fixture(scope="session")
def chromium() -> Path:
    try:
        return find_chromium()
    except BrowserUnavailable as error:
        pytest.skip(f"headless Chromium is needed to check the page: {error}")


def write_expanded_world(root: Path) -> Path:
    """A ``synthetic-olat`` dataset ``root/expanded``: subject x00, two cameras, in one frame the four rig
    lights alone, ``full`` and one environment-map-like lighting ``env-studio``.

    Rig light k has pattern ``olat-{3-k:03d}``, so rig order and pattern-name order differ."""
    folder = root / "expanded"
    provenance = Provenance("fit test sphere world", "CC0").derived("expansion of olat", "CC0")
    info = DatasetInfo(
        "expanded", "synthetic-olat", "sphere", "4 OLAT lights", provenance, fingerprint_config({})
    )
    writer = ShardWriter(folder, info)
    writer.begin()
    writer.write_lights(rig_lights(1.0, "rig", [f"olat-{3 - k:03d}" for k in range(len(LIGHTS))]))
    with writer.part("x00") as part:
        for c in (0, 1):
            K, w2c = sphere_camera(c)
            lightings = {
                f"olat-{3 - k:03d}": (p[None], [[EXPANDED_INTENSITY[k]] * 3]) for k, p in enumerate(LIGHTS)
            }
            lightings["full"] = (LIGHTS, [[v] * 3 for v in EXPANDED_INTENSITY])
            lightings["env-studio"] = (LIGHTS[[0, 2]], [[1.5, 1.2, 1.0]] * 2)
            for pattern, (positions, intensities) in lightings.items():
                image, mask = lambert_sphere(1.0, (0.6, 0.5, 0.4), K, w2c, positions, intensities)
                part.add(sphere_row("expanded", "x00", c, pattern, "test", image, mask))
    writer.commit()
    return folder


def picture(path: Path, colour: tuple[int, int, int], size=(40, 24)) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, colour).save(path)
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> ReportInputs:
    root = tmp_path_factory.mktemp("report-inputs")
    write_olat_world(root / "norm")
    write_flat_world(root / "norm")
    expanded = write_expanded_world(root / "expanded")
    (root / "norm" / "flat" / "quarantine.jsonl").write_text('{"item": "a"}\n{"item": "b"}\n')
    strip_frames = [Image.new("RGB", (48, 16), c) for c in ((200, 40, 40), (40, 200, 40), (40, 40, 200))]
    strip = root / "strips" / "env.webp"
    strip.parent.mkdir()
    strip_frames[0].save(
        strip, save_all=True, append_images=strip_frames[1:], duration=200, loop=0, lossless=True
    )
    evaluation = root / "evaluation"
    picture(evaluation / "grids" / "errors.png", (90, 30, 30))
    picture(evaluation / "grids" / "olat.png", (30, 90, 30))
    (evaluation / "report.md").write_text(EVALUATION_MD)
    (evaluation / "evaluation.json").write_text(
        json.dumps({"two-stage": {"psnr": 31.2}, "single": {"psnr": 27.9}})
    )
    metrics = root / "metrics.json"
    metrics.write_text(
        json.dumps(
            {
                "held_out": {"d1": {"psnr": 44.628103, "views": 18}, "d2": {"psnr": 24.25}},
                "iterations": 3000,
                "seconds_per_iteration": 0.46727865,
            }
        )
    )
    return ReportInputs(
        datasets=[root / "norm"],
        pictures=[("World preview", picture(root / "preview.png", (120, 100, 80)))],
        lighting_grid=picture(root / "lighting_grid.png", (60, 60, 120), size=(96, 64)),
        expanded=[expanded],
        strips=[("Studio envmap", strip), ("Folder of strips", strip.parent)],
        evaluation=evaluation,
        metrics=[("Stage 1", metrics)],
        title="tiny report",
    )


@pytest.fixture(scope="module")
def report(inputs, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("report") / "out"
    result = build_report(inputs, out, progress=False)
    assert result.warnings == []
    return out


def test_page_has_every_section_and_its_content(report):
    page = (report / "index.html").read_text()
    assert re.findall(r'<section id="([^"]+)"', page) == SECTIONS
    assert "not produced" not in page
    overview = page[page.index('id="datasets"') : page.index('id="pictures"')]
    # name, kind, subjects, cameras, frames (one per subject), images (2 x 4 cameras x 5 patterns + 4), lights,
    # quarantined
    cells = re.findall(r"<td[^>]*>([^<]*)</td>", overview)
    start = cells.index("olat")
    assert cells[start : start + 8] == ["olat", "olat", "3", "4", "3", "44", "4", "0"]
    assert cells[cells.index("flat") + 7] == "2"  # quarantine.jsonl lines
    assert "fit test sphere world (from" not in page  # the olat world has no parents
    assert "expansion of olat (from fit test sphere world)" in page
    # The Markdown table and list became HTML; its image points at the copied grid; the unlinked grid is shown too.
    assert "<td>single-stage</td>" in page and "<li>linear RGB, masked</li>" in page
    assert 'src="assets/evaluation/grids/errors.png"' in page and "grids/olat.png" in page
    assert "<td>held_out</td>" not in page and "<td>d1</td>" in page and "44.63" in page
    links = re.findall(r'(?:src|href)="([^"#]+)"', page)
    assert links and all((report / link).is_file() for link in links), "every link is a file in the folder"
    assert not any(link.startswith(("/", "http")) for link in links)


def test_olat_sheet_shows_every_light_in_rig_order_at_one_exposure(report):
    sheet = np.asarray(Image.open(report / "assets" / "expanded" / "00-expanded-x00.png"))
    tile, row = 96, 96 + 18
    assert sheet.shape[:2] == (2 * row, 3 * tile)  # full-on + 4 lights in a 3-column grid
    brightness = [
        sheet[r * row : r * row + tile, c * tile : (c + 1) * tile].mean() for r in (0, 1) for c in (0, 1, 2)
    ]
    # Tiles: full-on, then rig lights 0..3 (intensities 4, 2, 1, 0.25). A shared exposure keeps the
    # dimmest light dim, and rig order (not pattern-name order) puts it last.
    assert brightness[4] < 0.5 * max(brightness[1:4]) and brightness[4] > 0 and brightness[5] == 0
    envmaps = np.asarray(Image.open(report / "assets" / "expanded" / "01-expanded-x00-envmaps.png"))
    assert envmaps.shape[:2] == (row, tile)  # the one other lighting, env-studio


def test_every_image_loads_in_chromium(report, chromium, tmp_path):
    page = (report / "index.html").read_text()
    expected = page.count("<img ")
    screenshot = tmp_path / "page.png"
    seen = check_in_browser(report / "index.html", chromium, screenshot=screenshot)
    assert seen.sections == SECTIONS
    assert (seen.loaded, seen.total, seen.missing) == (expected, expected, [])
    assert expected >= 9  # 3 subject sheets, preview, lighting grid, OLAT sheet, 2 strips, 2 grids
    with Image.open(screenshot) as shot:
        assert shot.width > 500 and np.asarray(shot.convert("L")).std() > 5


def test_chromium_check_notices_a_missing_picture(report, chromium, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(report, broken)
    (broken / "assets" / "lighting" / "00-lighting-grid.png").unlink()
    seen = check_in_browser(broken / "index.html", chromium)
    assert not seen.ok
    assert seen.loaded == seen.total - 1 and seen.missing == ["assets/lighting/00-lighting-grid.png"]


def test_same_inputs_give_the_same_bytes(inputs, report, tmp_path):
    again = tmp_path / "again"
    build_report(inputs, again, progress=False)
    files = sorted(p.relative_to(report) for p in report.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert all((report / f).read_bytes() == (again / f).read_bytes() for f in files)


def test_missing_inputs_give_notes_warnings_and_no_crash(tmp_path):
    missing = tmp_path / "nowhere.png"
    evaluation = tmp_path / "evaluation"
    evaluation.mkdir()
    (evaluation / "report.md").write_text("# Eval\n\n![lost](grids/lost.png)\n")
    runner = CliRunner()
    result = runner.invoke(
        report_command,
        [
            "--out",
            str(tmp_path / "out"),
            "--image",
            f"Preview={missing}",
            "--evaluation",
            str(evaluation),
            "--metrics",
            f"Stage 1={tmp_path / 'metrics.json'}",
            "--quiet",
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"warning: Preview: {missing} does not exist" in result.output
    page = (tmp_path / "out" / "index.html").read_text()
    assert f"not produced: Preview: {missing} does not exist" in page
    assert "not produced: grids/lost.png" in page and "<img" not in page
    assert "not produced: no normalized datasets given" in page  # a section without input
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    with pytest.warns(ReportWarning, match="not a readable image"):
        second = build_report(ReportInputs(lighting_grid=broken), tmp_path / "second", progress=False)
    assert len(second.warnings) == 1 and second.images == 0


def test_metrics_tables_flatten_and_round():
    html = metrics_tables(
        {
            "a": {"b": {"c": 1.23456789}},
            "n": 7,
            "list": [1, 2.5],
            "matrix": {"x": {"p": 1.0, "q": 2}, "y": {"p": 0.333333}},
        }
    )
    assert '<td>a.b.c</td><td class="num">1.235</td>' in html
    assert '<td>n</td><td class="num">7</td>' in html and "[1, 2.5]" in html
    assert "<th>p</th><th>q</th>" in html and '<td>y</td><td class="num">0.3333</td><td></td>' in html


def test_markdown_links_are_rewritten_or_reported():
    converted = markdown_to_html(
        "# T\n\n![a](a.png) [doc](doc.txt) [web](https://x.org) ![w](http://x/y.png)"
    )
    missing = []
    rewritten = rewrite_links(
        converted, lambda link: "assets/a.png" if link == "a.png" else None, missing.append
    )
    assert "<h3>T</h3>" in rewritten and 'src="assets/a.png"' in rewritten
    assert (
        'href="https://x.org"' in rewritten and "external image http://x/y.png is not embedded" in rewritten
    )
    assert missing == ["http://x/y.png", "doc.txt"]


INJECTED_MD = """# Evaluation

<script>document.title = "injected"</script>

<div onclick="steal()">a block of raw HTML</div>

| subject | PSNR |
|---|---|
| d1/<img src=x onerror=alert(1)> | 30.1 |

[click](javascript:alert(1)) [data](data:text/html,<b>x</b>) [web](https://x.org) [secret](../secret.txt)
![outside](../outside.png) ![grid](grids/a%20(b).png)
"""


def test_raw_html_and_unsafe_links_in_report_md_never_reach_the_page(tmp_path):
    evaluation = tmp_path / "evaluation"
    picture(evaluation / "grids" / "a (b).png", (20, 120, 20))
    picture(tmp_path / "outside.png", (1, 2, 3))
    (tmp_path / "secret.txt").write_text("private")
    (evaluation / "report.md").write_text(INJECTED_MD)
    with pytest.warns(ReportWarning):  # evaluation.json is absent, and the links that leave the folder
        result = build_report(ReportInputs(evaluation=evaluation), tmp_path / "out", progress=False)
    page = (tmp_path / "out" / "index.html").read_text()
    section = page[
        page.index('<section id="evaluation">') : page.index("</section>", page.index('id="evaluation"'))
    ]
    assert page.count("<script>") == 1  # the page's own image check
    assert not re.search(r"<(script|div|img)\b[^>]*\b(onclick|onerror)|<div\b|<img src=\"?x", section), (
        section
    )
    assert "&lt;script&gt;" in section and "&lt;img src=x onerror=alert(1)&gt;" in section  # shown as text
    assert "javascript:" not in re.sub(r'data-refused="[^"]*"', "", section)
    assert 'href="data:' not in section and 'href="https://x.org"' in section
    copied = [p.name for p in (tmp_path / "out" / "assets").rglob("*") if p.is_file()]
    assert copied == ["a-b.png"], copied  # the grid in the folder, nothing from outside it
    assert "not produced: ../outside.png" in section and result.images == 1


def test_markdown_text_from_evaluation_names_stays_text():
    from relightanyone.evaluation.report import markdown_code, markdown_text

    name = "d1/<b>s</b> [x](javascript:alert(1)) | *y* `z` & \\"
    html = markdown_to_html(
        f"| subject | x |\n|---|---|\n| {markdown_text(name)} | 1 |\n\n- {markdown_code('a`b')}"
    )
    cells = re.findall(r"<td>(.*?)</td>", html)
    assert len(cells) == 2 and cells[1] == "1", html  # the pipe did not split the cell
    assert cells[0] == "d1/&lt;b&gt;s&lt;/b&gt; [x](javascript:alert(1)) | *y* `z` &amp; \\", cells[0]
    assert "<code>a`b</code>" in html
