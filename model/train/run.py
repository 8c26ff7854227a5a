"""Rendering a trained stage-1 run: a subject from its dataset's cameras or an orbit, under any
dataset's lighting code, and the lighting-alignment grid (one subject per dataset × every lighting code).

Swapping the lighting code only feeds the colour decoder, so the Gaussians' geometry stays identical;
the report measures that and the mean colour shift over the subject's foreground.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from relightanyone.align.colour import linear_to_display
from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import TEMPLATE_NAME
from relightanyone.model.networks.gaussians import Gaussians, load_template_binding
from relightanyone.model.networks.presets import Stage1Preset
from relightanyone.model.networks.render import grid, orbit_cameras, render_views, save_png
from relightanyone.model.networks.stage1 import Stage1Model
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.run_files import CHECKPOINT_NAME, read_run_info
from relightanyone.progress import progress_bar

FOREGROUND_ALPHA = 0.5
LIGHTING_GRID_NAME = "lighting_grid.png"
RENDER_REPORT_NAME = "render_report.json"
ORBIT_ELEVATION_DEG = 10.0


@dataclass
class Stage1Run:
    """A trained run: the model (eval mode, on the device it was loaded to) and what it was trained on."""

    path: Path
    model: Stage1Model
    subjects: list[str]
    datasets: list[str]
    dataset_dirs: list[Path]
    use_lighting: bool = True  # False for a colour warm-up run, which trained without lighting codes

    def subject_index(self, subject: str) -> int:
        """Index of ``<dataset>/<subject>``, or of a bare subject name when it is unique."""
        if subject in self.subjects:
            return self.subjects.index(subject)
        matches = [i for i, s in enumerate(self.subjects) if s.split("/", 1)[1] == subject]
        if len(matches) == 1:
            return matches[0]
        hint = (
            "it exists in several datasets, name it as <dataset>/<subject>" if matches else "unknown subject"
        )
        raise InputError(f"{self.path}: {hint}: {subject!r}; known: {', '.join(self.subjects[:12])}...")

    def dataset_index(self, name: str) -> int:
        if name not in self.datasets:
            raise InputError(
                f"{self.path}: unknown dataset {name!r} for --lighting-code; known: {', '.join(self.datasets)}"
            )
        return self.datasets.index(name)


def load_run(run_dir: Path, device: torch.device | str = "cpu") -> Stage1Run:
    """Rebuild the model of ``run_dir`` from its checkpoint, run.json and template copy, on ``device``."""

    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    checkpoint = load_checkpoint(run_dir / CHECKPOINT_NAME)
    preset = Stage1Preset.from_json(checkpoint["preset"])
    template_vertices, binding = load_template_binding(run_dir / TEMPLATE_NAME, preset.uv_size)
    model = Stage1Model(
        preset,
        template_vertices,
        binding,
        len(checkpoint["subjects"]),
        len(checkpoint["datasets"]),
        lighting_code=checkpoint.get("lighting_code", True),
    )
    model.load_state_dict(checkpoint["model"])
    model.to(device).eval()
    return Stage1Run(
        path=run_dir,
        model=model,
        subjects=list(checkpoint["subjects"]),
        datasets=list(checkpoint["datasets"]),
        dataset_dirs=[Path(d["path"]) for d in info["datasets"]],
        use_lighting=not checkpoint["warmup"],
    )


def subject_cameras(
    run: Stage1Run, subject_index: int, limit: int | None = None
) -> tuple[list[str], np.ndarray, np.ndarray, int, int]:
    """Full-on cameras of the subject's first frame in its dataset: names, K (C, 3, 3), w2c (C, 4, 4), width, height.

    Cameras whose image size differs from the first one are skipped (one render call per size).
    """

    dataset_name, subject = run.subjects[subject_index].split("/", 1)
    dataset = NormalizedDataset(run.dataset_dirs[run.datasets.index(dataset_name)])
    keys = dataset.select(subjects=subject, patterns="full")
    if not keys:
        raise InputError(f"{dataset.path}: no full-on rows of subject {subject!r}")
    first_frame = min(int(k.split("/")[2]) for k in keys)
    rows = [dataset.row(k) for k in keys if int(k.split("/")[2]) == first_frame]
    width, height = rows[0].width, rows[0].height
    rows = [r for r in rows if (r.width, r.height) == (width, height)][:limit]
    return (
        [r.camera for r in rows],
        np.stack([r.K for r in rows]),
        np.stack([r.w2c for r in rows]),
        width,
        height,
    )


@torch.no_grad()
def decode(run: Stage1Run, subject_index: int, lighting_index: int) -> Gaussians:
    device = run.model.identity_codes.device
    _, gaussians = run.model(
        torch.tensor([subject_index], device=device),
        torch.tensor([lighting_index], device=device),
        use_lighting=run.use_lighting,
    )
    return gaussians


def same_geometry(a: Gaussians, b: Gaussians) -> bool:
    """Whether two decodings have bit-identical positions, rotations, scales and opacities."""
    return all(torch.equal(getattr(a, n), getattr(b, n)) for n in ("means", "quats", "scales", "opacities"))


def mean_foreground_colour(images: torch.Tensor, alphas: torch.Tensor) -> np.ndarray:
    """Mean linear RGB over pixels with alpha > 0.5: images (C, 3, H, W), alphas (C, 1, H, W) -> (3,)."""
    weight = (alphas > FOREGROUND_ALPHA).float()
    return ((images * weight).sum(dim=(0, 2, 3)) / weight.sum().clamp(min=1.0)).cpu().numpy()


@torch.no_grad()
def render_with_alpha(gaussians: Gaussians, K: np.ndarray, w2c: np.ndarray, width: int, height: int):
    """Render one Gaussian set into C cameras given as numpy K (C, 3, 3) and w2c (C, 4, 4).

    Returns images (C, 3, H, W) and alphas (C, 1, H, W), on the Gaussians' device.
    """
    device = gaussians.means.device
    return render_views(
        gaussians,
        torch.tensor(K, dtype=torch.float32, device=device),
        torch.tensor(w2c, dtype=torch.float32, device=device),
        width,
        height,
    )


def render_subject(
    run: Stage1Run,
    subject: str,
    out_dir: Path,
    lighting_code: str | None = None,
    cameras: str = "dataset",
    orbit_count: int = 8,
) -> dict:
    """Write one PNG per camera of ``subject`` under ``lighting_code`` (default: its own dataset's).

    Returns a report: files, and when the lighting code is swapped, the mean foreground colour under
    both codes, their difference, and whether the geometry stayed identical.
    """
    subject_index = run.subject_index(subject)
    own_dataset = run.subjects[subject_index].split("/", 1)[0]
    lighting = lighting_code or own_dataset
    lighting_index = run.dataset_index(lighting)
    names, K, w2c, width, height = subject_cameras(run, subject_index)
    if cameras == "orbit":
        centre = np.zeros(3)
        radius = float(np.median([np.linalg.norm(np.linalg.inv(p)[:3, 3]) for p in w2c]))
        centred = K[0].copy()
        centred[:2, 2] = [(width - 1) / 2, (height - 1) / 2]  # dataset crops may be off-centre
        K, w2c = orbit_cameras(orbit_count, radius, centre, centred, ORBIT_ELEVATION_DEG)
        names = [f"orbit{i:03d}" for i in range(orbit_count)]
    elif cameras != "dataset":
        raise ValueError(f"--cameras must be 'dataset' or 'orbit', got {cameras!r}")
    gaussians = decode(run, subject_index, lighting_index)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    images, alphas = [], []
    for index in progress_bar(range(len(names)), desc=f"render {run.subjects[subject_index]}", unit="view"):
        image, alpha = render_with_alpha(
            gaussians, K[index : index + 1], w2c[index : index + 1], width, height
        )
        images.append(image)
        alphas.append(alpha)
    files = []
    safe_subject = run.subjects[subject_index].replace("/", "_")
    for name, image in zip(names, images, strict=True):
        path = out_dir / f"{safe_subject}_{lighting}_{name}.png"
        save_png(path, linear_to_display(image[0]).transpose(1, 2, 0))
        files.append(str(path))
    report = {
        "subject": run.subjects[subject_index],
        "lighting_code": lighting,
        "cameras": cameras,
        "files": files,
    }
    if lighting != own_dataset:
        own = decode(run, subject_index, run.dataset_index(own_dataset))
        own_images = [
            render_with_alpha(own, K[i : i + 1], w2c[i : i + 1], width, height) for i in range(len(names))
        ]
        swapped_colour = mean_foreground_colour(torch.cat(images), torch.cat(alphas))
        own_colour = mean_foreground_colour(
            torch.cat([i for i, _ in own_images]), torch.cat([a for _, a in own_images])
        )
        report.update(
            colour_shift_report(own_colour, swapped_colour, own_dataset, same_geometry(own, gaussians))
        )
    return report


def colour_shift_report(
    own: np.ndarray, swapped: np.ndarray, own_dataset: str, geometry_identical: bool
) -> dict:
    shift = swapped - own
    return {
        "own_lighting_code": own_dataset,
        "mean_colour_own": own.tolist(),
        "mean_colour_swapped": swapped.tolist(),
        "mean_colour_shift": shift.tolist(),
        "mean_colour_shift_norm": float(np.linalg.norm(shift)),
        "relative_colour_shift": float(np.linalg.norm(shift) / max(np.linalg.norm(own), 1e-12)),
        "geometry_identical": bool(geometry_identical),
    }


def lighting_alignment_grid(run: Stage1Run, out_path: Path) -> dict:
    """One training subject per dataset (rows) rendered under every dataset's lighting code (columns),
    from the subject's first dataset camera, into one PNG. Returns the colour shifts measured."""
    rows, shifts = [], {}
    size = None
    for dataset in progress_bar(run.datasets, desc="lighting grid", unit="subject"):
        subject_index = next(i for i, s in enumerate(run.subjects) if s.split("/", 1)[0] == dataset)
        _, K, w2c, width, height = subject_cameras(run, subject_index, limit=1)
        own = decode(run, subject_index, run.dataset_index(dataset))
        own_image, own_alpha = render_with_alpha(own, K, w2c, width, height)
        row = []
        for lighting in run.datasets:
            gaussians = (
                own if lighting == dataset else decode(run, subject_index, run.dataset_index(lighting))
            )
            image, alpha = (
                (own_image, own_alpha)
                if lighting == dataset
                else render_with_alpha(gaussians, K, w2c, width, height)
            )
            display = linear_to_display(image[0]).transpose(1, 2, 0)
            size = size or display.shape[:2]
            row.append(_fit(display, size))
            if lighting != dataset:
                shifts[f"{run.subjects[subject_index]} under {lighting}"] = colour_shift_report(
                    mean_foreground_colour(own_image, own_alpha),
                    mean_foreground_colour(image, alpha),
                    dataset,
                    same_geometry(own, gaussians),
                )
        rows.append(row)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_png(out_path, grid(rows))
    return {"file": str(out_path), "rows": run.datasets, "columns": run.datasets, "shifts": shifts}


def _fit(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize (H, W, 3) uint8 to ``size`` (H, W) so datasets of different image sizes share a grid."""
    if image.shape[:2] == tuple(size):
        return image
    from PIL import Image

    return np.asarray(Image.fromarray(image).resize((size[1], size[0]), Image.BILINEAR))


def render_run(
    run_dir: Path,
    out: Path,
    subject: str | None = None,
    lighting_code: str | None = None,
    cameras: str = "dataset",
    orbit_count: int = 8,
    lighting_grid: bool = False,
    device: torch.device | str = "cpu",
) -> dict:
    """What ``relightanyone render stage1`` writes into ``out``: ``subject``'s PNGs
    (:func:`render_subject`), with ``lighting_grid`` also ``lighting_grid.png``
    (:func:`lighting_alignment_grid`), and ``render_report.json``, the reports it returns."""
    run = load_run(run_dir, device)
    out = Path(out)
    reports = {}
    if subject is not None:
        reports["subject"] = render_subject(run, subject, out, lighting_code, cameras, orbit_count)
    if lighting_grid:
        reports["lighting_grid"] = lighting_alignment_grid(run, out / LIGHTING_GRID_NAME)
    out.mkdir(parents=True, exist_ok=True)
    (out / RENDER_REPORT_NAME).write_text(json.dumps(reports, indent=2) + "\n")
    return reports
