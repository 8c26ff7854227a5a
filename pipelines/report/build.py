"""``relightanyone report``: one self-contained HTML page of everything a run produced.

``build_report(ReportInputs(...), out)`` writes ``out/index.html`` and ``out/assets/`` (every picture
copied or generated there, relative links only, inline CSS, no network resources), so the folder can be
zipped and opened anywhere. Sections, in order:

``datasets``    overview table of the normalized datasets (manifest counts, quarantined items,
                provenance) and one subject sheet per dataset
``pictures``    contact sheets and other pictures given by title
``lighting``    the lighting-alignment grid of a stage-1 run
``expanded``    OLAT contact sheets of the expanded (``synthetic-olat``) datasets, one per subject
``relighting``  environment-map relighting strips (PNG sheets, animated WebP/GIF)
``evaluation``  the evaluation's ``report.md`` as HTML, its grids, and ``evaluation.json``
``metrics``     stage metrics JSON files as tables of scalars

Every input is optional. A section without input shows a ``not produced`` note; an input that was given
but is missing or unreadable shows the note too, is listed in the page's warnings box and raises a
``ReportWarning``. Output is deterministic: the same inputs give the same bytes.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

from relightanyone.format.reader import IncompleteDatasetError, NormalizedDataset
from relightanyone.format.schema import SchemaError
from relightanyone.format.shards import dataset_dirs
from relightanyone.pipelines.report.assets import IMAGE_SUFFIXES, AssetStore, UnreadablePicture
from relightanyone.pipelines.report.html import (
    Section,
    esc,
    figure,
    markdown_to_html,
    not_produced,
    note,
    page,
    rewrite_links,
    table,
)
from relightanyone.pipelines.report.metrics import metrics_tables
from relightanyone.pipelines.report.sheets import OVERVIEW_HEADER, olat_sheets, overview_row, subject_sheet
from relightanyone.progress import progress_bar

LIGHTING_GRID_CAPTION = (
    "Rows: one training subject of each dataset; columns: that subject decoded with each dataset's "
    "lighting code. Only colour and brightness should change along a row (the geometry stays)."
)


class ReportWarning(UserWarning):
    """An input of the report was given but is missing or unreadable (the page shows a note)."""


@dataclass
class ReportInputs:
    """What goes into the report; every field may be empty.

    ``pictures`` and ``strips`` are (title, path) pairs (a strip path may be a folder of pictures);
    ``metrics`` are (title, JSON path) pairs; ``datasets`` are folders holding one dataset per
    sub-folder (or a dataset folder itself).
    """

    datasets: list[Path] = field(default_factory=list)
    pictures: list[tuple[str, Path]] = field(default_factory=list)
    lighting_grid: Path | None = None
    expanded: list[Path] = field(default_factory=list)
    strips: list[tuple[str, Path]] = field(default_factory=list)
    evaluation: Path | None = None
    metrics: list[tuple[str, Path]] = field(default_factory=list)
    title: str = "relightanyone report"
    subject_sheets: bool = True
    max_subjects: int = 24
    olat_camera: str | None = None


@dataclass
class ReportResult:
    """Where the page was written, how many pictures it links, and the warnings it shows."""

    index: Path
    images: int
    warnings: list[str]


class _Builder:
    """Collects assets and warnings while the sections are built."""

    def __init__(self, staging: Path, progress: bool):
        self.assets = AssetStore(staging)
        self.warnings: list[str] = []
        self.progress = progress

    def warn(self, message: str) -> str:
        """Record a warning and return its ``not produced`` note for the page."""
        self.warnings.append(message)
        warnings.warn(message, ReportWarning, stacklevel=3)
        return not_produced(message)

    def picture(self, section: str, title: str, path: Path, caption: str | None = None) -> str:
        path = Path(path)
        if not path.is_file():
            return self.warn(f"{title}: {path} does not exist")
        try:
            url = self.assets.add_picture(section, title, path)
        except UnreadablePicture as error:
            return self.warn(f"{title}: {error}")
        return figure(url, caption or title)


def _dataset_folders(parents: list[Path]) -> list[Path]:

    found: list[Path] = []
    for parent in parents:
        if Path(parent).is_dir():
            found.extend(dataset_dirs(Path(parent)))
    return found


def _datasets_section(builder: _Builder, inputs: ReportInputs) -> str:

    if not inputs.datasets and not inputs.expanded:
        return not_produced("no normalized datasets given (--datasets)")
    body = []
    for parent in inputs.datasets:
        if not Path(parent).is_dir():
            body.append(builder.warn(f"datasets: {parent} is not a folder"))
        elif not _dataset_folders([parent]):
            body.append(builder.warn(f"datasets: {parent} holds no normalized dataset (no manifest.json)"))
    folders, seen = [], set()
    for folder in [
        *_dataset_folders(inputs.datasets),
        *[Path(p) for p in inputs.expanded if Path(p).is_dir()],
    ]:
        if folder.resolve() not in seen:
            seen.add(folder.resolve())
            folders.append(folder)
    rows = [overview_row(folder) for folder in folders]
    for row in rows:
        if row.problem:
            body.append(builder.warn(row.problem))
    good = [row for row in rows if not row.problem]
    if good:
        body.append(table(OVERVIEW_HEADER, [row.cells() for row in good]))
        lighting = [(row.name, row.lighting) for row in good if row.lighting]
        if lighting:
            items = "".join(f"<li><strong>{esc(n)}</strong>: {esc(text)}</li>" for n, text in lighting)
            body.append(f'<p class="muted">Lighting:</p><ul class="muted">{items}</ul>\n')
    if inputs.subject_sheets:
        for row in progress_bar(good, desc="subject sheets", unit="dataset", disable=not builder.progress):
            try:
                dataset = NormalizedDataset(row.path)
                if len(dataset) == 0:
                    body.append(not_produced(f"{row.name}: the dataset has no images"))
                    continue
                sheet, caption = subject_sheet(dataset, inputs.max_subjects)
            except (OSError, ValueError, RuntimeError) as error:
                body.append(builder.warn(f"{row.path}: cannot draw the subject sheet ({error})"))
                continue
            body.append(figure(builder.assets.add_array("datasets", row.name, sheet), caption))
    return "".join(body)


def _pictures_section(builder: _Builder, inputs: ReportInputs) -> str:
    if not inputs.pictures:
        return not_produced("no pictures given (--image TITLE=PATH)")
    return "".join(builder.picture("pictures", title, path) for title, path in inputs.pictures)


def _lighting_section(builder: _Builder, inputs: ReportInputs) -> str:
    if inputs.lighting_grid is None:
        return not_produced("no lighting-alignment grid given (--lighting-grid PATH)")
    caption = f"Lighting-alignment grid. {LIGHTING_GRID_CAPTION}"
    return builder.picture("lighting", "lighting grid", inputs.lighting_grid, caption)


def _expanded_section(builder: _Builder, inputs: ReportInputs) -> str:

    if not inputs.expanded:
        return not_produced("no expanded datasets given (--expanded DIR)")
    body = []
    for folder in inputs.expanded:
        try:
            dataset = NormalizedDataset(folder)
        except (IncompleteDatasetError, SchemaError, OSError) as error:
            body.append(builder.warn(f"expanded: {error}"))
            continue
        kind = dataset.manifest.info.kind
        heading = f'<h3>{esc(dataset.name)} <span class="muted">({esc(kind)}, {esc(folder)})</span></h3>\n'
        body.append(heading)
        if kind != "synthetic-olat":
            body.append(
                note(f"{dataset.name} is of kind {kind!r}, not 'synthetic-olat'; its OLAT images are shown")
            )
        count = 0
        for sheet in olat_sheets(dataset, inputs.olat_camera, inputs.max_subjects, progress=builder.progress):
            url = builder.assets.add_array("expanded", f"{dataset.name}-{sheet.subject}", sheet.image)
            caption = (
                f"{dataset.name} / {sheet.subject}: camera {sheet.camera}, {_frames_text(sheet.frames)}, "
                f"{sheet.lights} lights at one exposure (x{sheet.exposure:.3g}, linear to sRGB)"
            )
            body.append(figure(url, caption))
            if sheet.envmap_image is not None:
                url = builder.assets.add_array(
                    "expanded", f"{dataset.name}-{sheet.subject}-envmaps", sheet.envmap_image
                )
                caption = (
                    f"{dataset.name} / {sheet.subject}: camera {sheet.camera} under its {sheet.envmaps} other "
                    "lightings (environment maps), each at its own exposure"
                )
                body.append(figure(url, caption))
            count += 1
        if count == 0:
            body.append(builder.warn(f"expanded: {folder} has no OLAT images (patterns olat-NNN)"))
        elif len(dataset.subjects) > inputs.max_subjects:
            body.append(note(f"showing {inputs.max_subjects} of {len(dataset.subjects)} subjects"))
    return "".join(body)


def _frames_text(frames: list[int]) -> str:
    if len(frames) == 1:
        return f"frame {frames[0]}"
    return f"frames {frames[0]} to {frames[-1]}"


def _strips_section(builder: _Builder, inputs: ReportInputs) -> str:
    if not inputs.strips:
        return not_produced("no relighting strips given (--strip TITLE=PATH)")
    body = []
    for title, path in inputs.strips:
        path = Path(path)
        if path.is_dir():
            pictures = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not pictures:
                body.append(builder.warn(f"{title}: the folder {path} holds no pictures"))
            body.append(f"<h3>{esc(title)}</h3>\n")
            body.extend(builder.picture("relighting", f"{title}-{p.stem}", p, p.name) for p in pictures)
        else:
            body.append(builder.picture("relighting", title, path))
    return "".join(body)


def _evaluation_section(builder: _Builder, inputs: ReportInputs) -> str:
    folder = inputs.evaluation
    if folder is None:
        return not_produced("no evaluation folder given (--evaluation DIR)")
    folder = Path(folder)
    if not folder.is_dir():
        return builder.warn(f"evaluation: {folder} is not a folder")
    body, linked = [], set()

    def resolve(link: str) -> str | None:
        target = (folder / unquote(link.split("#", 1)[0])).resolve()
        # Only files of the evaluation folder: a link in report.md must not copy other files into the page.
        if not target.is_file() or not target.is_relative_to(folder.resolve()):
            return None
        linked.add(target)
        return builder.assets.add_file("evaluation", os.path.relpath(target, folder.resolve()), target)

    markdown_path = folder / "report.md"
    if markdown_path.is_file():
        converted = markdown_to_html(markdown_path.read_text("utf-8"))
        body.append(
            rewrite_links(
                converted, resolve, lambda link: builder.warn(f"{markdown_path}: links to missing {link}")
            )
        )
    else:
        body.append(builder.warn(f"evaluation: {markdown_path} does not exist"))
    grids = sorted(p for p in (folder / "grids").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    unlinked = [p for p in grids if p.resolve() not in linked]
    if not grids:
        body.append(builder.warn(f"evaluation: no pictures in {folder / 'grids'}"))
    elif unlinked:
        body.append("<h3>Grids</h3>\n")
        body.extend(builder.picture("evaluation-grids", p.stem, p, f"grids/{p.name}") for p in unlinked)
    json_path = folder / "evaluation.json"
    if json_path.is_file():
        url = builder.assets.add_file("evaluation", "evaluation.json", json_path)
        try:
            tables = metrics_tables(json.loads(json_path.read_text("utf-8")))
        except json.JSONDecodeError as error:
            body.append(builder.warn(f"{json_path}: not valid JSON ({error})"))
        else:
            body.append(
                f'<details><summary>All numbers of <a href="{esc(url)}">evaluation.json</a></summary>\n'
            )
            body.append(tables + "</details>\n")
    else:
        body.append(builder.warn(f"evaluation: {json_path} does not exist"))
    return "".join(body)


def _metrics_section(builder: _Builder, inputs: ReportInputs) -> str:
    if not inputs.metrics:
        return not_produced("no metrics files given (--metrics TITLE=PATH)")
    body = []
    for number, (title, path) in enumerate(inputs.metrics):
        path = Path(path)
        body.append(f"<h3>{esc(title)}</h3>\n")
        if not path.is_file():
            body.append(builder.warn(f"{title}: {path} does not exist"))
            continue
        try:
            values = json.loads(path.read_text("utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            body.append(builder.warn(f"{title}: {path} is not valid JSON ({error})"))
            continue
        url = builder.assets.add_file("metrics", f"{number:02d}-{path.name}", path)
        body.append(f'<p class="muted">from <a href="{esc(url)}">{esc(path.name)}</a></p>\n')
        body.append(metrics_tables(values))
    return "".join(body)


SECTIONS = (
    ("datasets", "Datasets", _datasets_section),
    ("pictures", "Contact sheets and pictures", _pictures_section),
    ("lighting", "Lighting alignment", _lighting_section),
    ("expanded", "Expanded datasets: OLAT contact sheets", _expanded_section),
    ("relighting", "Environment-map relighting", _strips_section),
    ("evaluation", "Evaluation", _evaluation_section),
    ("metrics", "Stage metrics", _metrics_section),
)


def _install(staging: Path, out: Path) -> None:
    """Move the staged ``index.html`` and ``assets/`` into ``out``, replacing an earlier report's."""
    out.mkdir(parents=True, exist_ok=True)
    if (out / "assets").exists():
        shutil.rmtree(out / "assets")
    if (staging / "assets").exists():
        os.replace(staging / "assets", out / "assets")
    os.replace(staging / "index.html", out / "index.html")


def build_report(inputs: ReportInputs, out: Path, progress: bool = True) -> ReportResult:
    """Write ``out/index.html`` and ``out/assets/`` from ``inputs``; see the module docstring.

    The page is built in a temporary folder beside ``out`` and moved in at the end, so an interrupted
    run leaves the previous report as it was. Other files in ``out`` are left alone.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent) as staging_name:
        staging = Path(staging_name)
        builder = _Builder(staging, progress)
        sections = [Section(anchor, title, build(builder, inputs)) for anchor, title, build in SECTIONS]
        html_text = page(
            inputs.title,
            "Scene-linear images are shown as sRGB previews; numbers are rounded for display.",
            sections,
            builder.warnings,
        )
        (staging / "index.html").write_text(html_text, encoding="utf-8")
        _install(staging, out)
    images = html_text.count("<img ")
    return ReportResult(out / "index.html", images, builder.warnings)
