"""What the report shows of normalized datasets: the overview row, a subject sheet, OLAT contact sheets.

The overview reads only ``manifest.json`` and ``quarantine.jsonl`` (fast even for large datasets). The
pictures decode a few rows through ``NormalizedDataset``: one full-on view per subject for the subject
sheet, and for an expanded (``synthetic-olat``) dataset one camera of each subject under every light.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relightanyone.format.preview import linear_to_srgb_preview, render_contact_sheet
from relightanyone.format.schema import MANIFEST_NAME, QUARANTINE_NAME
from relightanyone.progress import progress_bar

OVERVIEW_HEADER = (
    "dataset",
    "kind",
    "subjects",
    "cameras",
    "frames",
    "images",
    "lights",
    "quarantined",
    "source dataset",
    "licence",
)
OLAT_PATTERN = re.compile(r"^olat-\d+$")


@dataclass
class OverviewRow:
    """One dataset of the overview table; ``problem`` is set (and counts empty) for an unreadable folder."""

    path: Path
    name: str
    kind: str = ""
    counts: dict | None = None
    quarantined: int | None = None
    source_dataset: str = ""
    licence: str = ""
    lighting: str = ""
    problem: str = ""

    def cells(self) -> list[object]:
        """Cells in ``OVERVIEW_HEADER`` order."""
        counts = self.counts or {}
        numbers = [counts.get(k, "") for k in ("subjects", "cameras", "frames", "images", "lights")]
        quarantined = "" if self.quarantined is None else self.quarantined
        return [self.name, self.kind, *numbers, quarantined, self.source_dataset, self.licence]


def _source_description(provenance: dict) -> str:
    """``source`` or ``source (from A; B)`` for a derived dataset, following the parents one level.

    A parent's details (paths, hashes) stay in manifest.json: the table names it only.
    """
    source = str(provenance.get("source_dataset", ""))
    parents = [
        re.split(r" \(| (?=/)| sha256:", str(p.get("source_dataset", "")), maxsplit=1)[0]
        for p in provenance.get("parents", [])
        if isinstance(p, dict)
    ]
    return f"{source} (from {'; '.join(parents)})" if parents else source


def count_quarantine_lines(path: Path) -> int:
    """Non-empty lines of a ``quarantine.jsonl`` (0 when the file is absent)."""
    if not path.exists():
        return 0
    return sum(1 for line in path.read_text("utf-8").splitlines() if line.strip())


def overview_row(dataset_dir: Path) -> OverviewRow:
    """The overview row of one dataset folder, from its manifest; never raises for a bad folder."""
    dataset_dir = Path(dataset_dir)
    manifest_path = dataset_dir / MANIFEST_NAME
    if not manifest_path.exists():
        return OverviewRow(
            dataset_dir, dataset_dir.name, problem=f"{dataset_dir}: no {MANIFEST_NAME} (incomplete dataset)"
        )
    try:
        manifest = json.loads(manifest_path.read_text("utf-8"))
        provenance = manifest.get("provenance") or {}
        return OverviewRow(
            path=dataset_dir,
            name=str(manifest["dataset"]),
            kind=str(manifest["kind"]),
            counts={k: int(v) for k, v in manifest["counts"].items()},
            quarantined=count_quarantine_lines(dataset_dir / QUARANTINE_NAME),
            source_dataset=_source_description(provenance),
            licence=str(provenance.get("licence", "")),
            lighting=str(manifest.get("lighting", "")),
        )
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as error:
        return OverviewRow(
            dataset_dir, dataset_dir.name, problem=f"{manifest_path}: unreadable manifest ({error!r})"
        )


@dataclass(frozen=True)
class IndexEntry:
    """The index fields of one image row (no image bytes are read)."""

    key: str
    frame: int
    camera: str
    pattern: str


def index_entries(dataset) -> dict[str, IndexEntry]:
    """Key -> ``IndexEntry`` for every row of a ``NormalizedDataset``, from its small ``index.arrow``."""
    columns = [dataset.index.column(c).to_pylist() for c in ("key", "frame", "camera", "pattern")]
    return {
        key: IndexEntry(key, int(frame), camera, pattern)
        for key, frame, camera, pattern in zip(*columns, strict=True)
    }


def _pick_camera(cameras: list[str], wanted: str | None) -> str:
    """``wanted`` when the subject has it, else the middle camera in sorted order (often a frontal one)."""
    if wanted is not None and wanted in cameras:
        return wanted
    return cameras[len(cameras) // 2]


def subject_sheet(dataset, max_subjects: int, tile: int = 160) -> tuple[np.ndarray, str]:
    """One full-on view per subject of a ``NormalizedDataset``: ((H, W, 3) uint8 sheet, caption).

    Each tile is the subject's first frame, ``full`` pattern (or its first pattern), middle camera, with
    the mask outlined; exposure is automatic per tile.
    """

    subjects = dataset.subjects[:max_subjects]
    index = index_entries(dataset)
    images, masks, labels = [], [], []
    for subject in subjects:
        keys = dataset.select(subjects=subject, patterns="full") or dataset.select(subjects=subject)
        entries = [index[k] for k in keys]
        first_frame = min(e.frame for e in entries)
        entries = [e for e in entries if e.frame == first_frame]
        camera = _pick_camera(sorted({e.camera for e in entries}), None)
        row, image, mask = dataset.decoded(next(e.key for e in entries if e.camera == camera))
        images.append(image)
        masks.append(mask)
        labels.append(f"{subject} {row.camera} {row.pattern}")
    shown = (
        f"{len(subjects)} of {len(dataset.subjects)} subjects"
        if len(dataset.subjects) > len(subjects)
        else (f"{len(subjects)} subject(s)")
    )
    caption = f"{dataset.name}: {shown}, one view each (first frame, mask outlined, automatic exposure)"
    return render_contact_sheet(images, masks, labels, tile=tile, columns=min(len(images), 8)), caption


@dataclass
class OlatSheet:
    """The contact sheets of one subject of an expanded dataset, as (H, W, 3) uint8 sRGB.

    ``image``: every rig light alone at one shared ``exposure`` (after a ``full`` tile when present);
    ``envmap_image``: the other lightings (environment maps), each at its own exposure, or ``None``.
    """

    subject: str
    camera: str
    frames: list[int]
    lights: int
    exposure: float
    image: np.ndarray
    envmap_image: np.ndarray | None = None
    envmaps: int = 0


def shared_exposure(images: list[np.ndarray], percentile: float = 99.5) -> float:
    """One exposure for a set of linear images: their joint ``percentile`` of lit pixel values -> 0.9.

    Sharing it keeps the relative brightness of the lights visible across the tiles of a sheet.
    """
    lit = [im[im.max(axis=-1) > 1e-4] for im in images]
    values = np.concatenate([v.reshape(-1) for v in lit]) if lit else np.zeros(0)
    reference = float(np.percentile(values, percentile)) if values.size else 0.0
    return 0.9 / reference if reference > 0 else 1.0


def rig_patterns(dataset) -> list[str]:
    """The dataset's one-light patterns in rig order: those of ``lights.arrow`` that have images, else
    the ``olat-NNN`` patterns."""
    present = set(dataset.patterns)
    ordered = [str(light["pattern"]) for light in sorted(dataset.lights(), key=lambda light: light["index"])]
    from_rig = [p for p in ordered if p in present]
    return from_rig or [p for p in dataset.patterns if OLAT_PATTERN.match(p)]


def _first_per_pattern(entries: list[IndexEntry], order: list[str]) -> list[IndexEntry]:
    """The earliest-frame entry of each pattern, in the order of ``order``."""
    rank = {p: i for i, p in enumerate(order)}
    first: dict[str, IndexEntry] = {}
    for entry in sorted(entries, key=lambda e: (rank[e.pattern], e.frame)):
        first.setdefault(entry.pattern, entry)
    return list(first.values())


def olat_sheets(dataset, camera: str | None, max_subjects: int, tile: int = 96, progress: bool = True):
    """Yield an ``OlatSheet`` per subject (at most ``max_subjects``) of an expanded dataset.

    One camera per subject (``camera`` when the subject has it, else the middle one of those with
    one-light images). One tile per rig light in rig order, each from the first frame that has it (an
    expansion puts all lights in one frame; a light stage spreads them over frames), labelled with the
    light's name, all at one shared exposure; the first ``full`` image of that camera, when present,
    comes first at its own exposure. Patterns that are neither rig lights nor ``full`` (the expansion's
    environment maps, ``env-<name>``) form a second sheet, each tile at its own exposure.
    """
    light_names = {str(light["pattern"]): str(light["name"]) for light in dataset.lights()}
    olat_patterns = rig_patterns(dataset)
    other_patterns = [p for p in dataset.patterns if p not in set(olat_patterns) | {"full"}]
    index = index_entries(dataset)
    for subject in progress_bar(
        dataset.subjects[:max_subjects],
        desc=f"OLAT sheets {dataset.name}",
        unit="subject",
        disable=not progress,
    ):
        rows = [index[k] for k in dataset.select(subjects=subject, patterns=olat_patterns)]
        if not rows:
            continue
        chosen = _pick_camera(sorted({r.camera for r in rows}), camera)
        view = _first_per_pattern([r for r in rows if r.camera == chosen], olat_patterns)
        linear = [dataset.decoded(r.key)[1] for r in view]
        exposure = shared_exposure(linear)
        tiles = [linear_to_srgb_preview(im, exposure) for im in linear]
        labels = [light_names.get(r.pattern, r.pattern) for r in view]
        frames = sorted({r.frame for r in view})
        full_keys = dataset.select(subjects=subject, cameras=chosen, patterns="full")
        if full_keys:
            full_entry = min((index[k] for k in full_keys), key=lambda r: (r.frame not in frames, r.frame))
            tiles.insert(0, linear_to_srgb_preview(dataset.decoded(full_entry.key)[1]))
            labels.insert(0, "full-on")
        image = render_contact_sheet(tiles, [None] * len(tiles), labels, tile=tile)
        sheet = OlatSheet(subject, chosen, frames, len(view), exposure, image)
        other_keys = (
            dataset.select(subjects=subject, cameras=chosen, patterns=other_patterns)
            if other_patterns
            else []
        )
        if other_keys:
            relit = _first_per_pattern([index[k] for k in other_keys], other_patterns)
            sheet.envmap_image = render_contact_sheet(
                [linear_to_srgb_preview(dataset.decoded(r.key)[1]) for r in relit],
                [None] * len(relit),
                [r.pattern for r in relit],
                tile=tile,
                columns=min(len(relit), 8),
            )
            sheet.envmaps = len(relit)
        yield sheet
