"""The OLAT expansion job: relight every subject of a flat-lit normalized dataset under every light of the
OLAT rig with the two-stage model and write the result as a normalized dataset of kind ``synthetic-olat``.

For each selected subject (one task): build its avatar (decoded from its stage-1 identity code with the OLAT
dataset's lighting code when stage 1 was trained on it, else fitted to its full-on views, see
:mod:`relightanyone.pipelines.expand.avatar`), then for its first full-on frame (or every frame) and every
camera of that frame render ``olat-KKK`` for each rig light, ``full`` (the whole rig at calibrated
intensities) and ``env-<name>`` per environment map. Rows keep the source row's K, w2c, size, mask, crop
and split; ``source`` is the source row key and ``source_sha256`` the sha256 of its encoded image.

Each task writes one :class:`~relightanyone.format.shards.ShardWriter` part and returns a small report, so
the coordinator never holds pixels, a finished subject is skipped on a re-run and a killed run resumes
without duplicates; the commit sorts rows by key, so the bytes do not depend on the executor
(:mod:`relightanyone.parallel`) or the worker count (tasks run with fixed torch threads and seeds).
"""

from __future__ import annotations

import hashlib
import re
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

from relightanyone.errors import InputError
from relightanyone.format.reader import NormalizedDataset, load_manifest
from relightanyone.format.schema import (
    LIGHTS_NAME,
    MANIFEST_NAME,
    DatasetInfo,
    LightRow,
    Manifest,
    check_name,
    fingerprint_config,
)
from relightanyone.format.shards import ShardWriter
from relightanyone.hashing import sha256_file
from relightanyone.model.device import resolve_device
from relightanyone.model.fit.fitter import FitSettings
from relightanyone.model.train.run_files import read_run_info
from relightanyone.parallel import Executor, TaskResources
from relightanyone.pipelines.expand.inputs import (
    checkpoint_sha256,
    dataset_provenance,
    load_model_early,
    stage2_olat_dataset,
)
from relightanyone.pipelines.expand.render import envmap_pattern
from relightanyone.pipelines.expand.task import run_expand_task
from relightanyone.progress import progress_bar

TASK_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
# What the local pool's server imports once, so each forked worker starts with them loaded.
WORKER_PRELOAD = (
    "torch",
    "relightanyone.pipelines.expand.task",
    "relightanyone.pipelines.expand.render",
    "relightanyone.pipelines.expand.avatar",
    "relightanyone.model.fit.fitter",
    "relightanyone.format.shards",
)


@dataclass(frozen=True)
class ExpandSettings:
    """Everything a task needs; plain paths and numbers, so it pickles to process-pool and Ray workers.

    fit_iterations: (inversion, finetuning) steps for subjects stage 1 does not know.
    device: a torch device name such as "cpu" or "cuda:1" (resolved, never "auto").
    threads: torch intra-op threads per task.
    """

    source: Path
    stage1: Path
    stage2: Path
    output: Path
    avatars: Path
    envmaps: tuple[Path, ...] = ()
    fit_iterations: tuple[int, int] = (300, 300)
    fit_image_scale: float = 1.0
    all_frames: bool = False
    device: str = "cpu"
    threads: int = 1
    seed: int = 0
    lightings_per_pass: int = 16

    def fit_settings(self):

        return FitSettings(
            inversion_iterations=self.fit_iterations[0],
            finetune_iterations=self.fit_iterations[1],
            seed=self.seed,
            progress=False,
        )


@dataclass(frozen=True)
class ExpandTask:
    """One subject: its part name, source rows (full-on, chosen frames), and its stage-1 code if known."""

    subject: str
    name: str
    source_keys: tuple[str, ...]
    frames: tuple[int, ...]
    stage1_index: int | None
    split: str
    fit_fingerprint: str = ""  # inputs of the fit of an unknown subject; "" for a decoded one

    @property
    def known(self) -> bool:
        return self.stage1_index is not None


@dataclass
class ExpansionPlan:
    """What a run will do: the dataset info, the tasks, the rig pattern names and the image count."""

    info: DatasetInfo
    settings: ExpandSettings
    tasks: list[ExpandTask]
    light_rows: list[dict]
    patterns: list[str]
    inputs: dict = field(default_factory=dict)

    @property
    def image_count(self) -> int:
        return sum(len(t.source_keys) for t in self.tasks) * len(self.patterns)

    def summary(self) -> dict:
        return {
            "output": str(self.settings.output),
            "kind": self.info.kind,
            "config_fingerprint": self.info.config_fingerprint,
            "patterns": self.patterns,
            "images": self.image_count,
            "subjects": [
                {
                    "subject": t.subject,
                    "split": t.split,
                    "avatar": "decoded" if t.known else "fitted",
                    "frames": list(t.frames),
                    "views": len(t.source_keys),
                }
                for t in self.tasks
            ],
        }


def task_name(subject: str) -> str:
    """The subject itself when it is a valid part name, else a readable prefix plus a short hash."""
    if TASK_NAME.match(subject) and not subject.endswith(".tmp"):
        return subject
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", subject).strip("._-") or "subject"
    return f"{cleaned[:40]}-{hashlib.sha256(subject.encode()).hexdigest()[:10]}"


def plan_expansion(
    source: Path,
    stage1: Path,
    stage2: Path,
    parent: Path,
    name: str | None = None,
    subjects: Sequence[str] | None = None,
    splits: Sequence[str] | None = None,
    envmaps: list[Path] | None = None,
    fit_iterations: tuple[int, int] = (300, 300),
    fit_image_scale: float = 1.0,
    all_frames: bool = False,
    device: str = "auto",
    seed: int = 0,
    lightings_per_pass: int = 16,
) -> ExpansionPlan:
    """Check the inputs (loading both runs together once) and list the tasks; renders nothing."""

    source_data = NormalizedDataset(source)
    name = check_name(name or f"{source_data.name}-olat", "dataset", "expand --name")
    for envmap in envmaps or []:
        check_name(envmap_pattern(Path(envmap)), "pattern", str(envmap))
    if min(fit_iterations) < 0:
        raise InputError(f"--fit-iterations must be >= 0, got {fit_iterations}")
    envmaps = [Path(p) for p in envmaps or []]
    for path in envmaps:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: environment map not found")
    olat_dir = stage2_olat_dataset(stage2)
    light_rows = NormalizedDataset(olat_dir).lights()
    if not light_rows:
        raise InputError(f"{olat_dir}: the stage-2 run's OLAT dataset has no lights.arrow rows")
    inputs = {
        "source_manifest_sha256": sha256_file(source_data.path / MANIFEST_NAME),
        "source_config_fingerprint": source_data.manifest.info.config_fingerprint,
        "stage1_checkpoint_sha256": checkpoint_sha256(stage1, "stage-1"),
        "stage2_checkpoint_sha256": checkpoint_sha256(stage2, "stage-2"),
        "olat_lights_sha256": sha256_file(olat_dir / LIGHTS_NAME),
        "envmaps_sha256": {envmap_pattern(p): sha256_file(p) for p in envmaps},
    }
    read_run_info(stage1, "stage1")
    stage1_subjects = load_model_early(stage1, stage2)

    index = source_data.index
    keys = index.column("key").to_pylist()
    columns = {c: index.column(c).to_pylist() for c in ("subject", "frame", "pattern", "split")}
    full_rows = [i for i, p in enumerate(columns["pattern"]) if p == "full"]
    if not full_rows:
        raise InputError(f"{source_data.path}: no full-on rows (pattern 'full') to expand")
    available = sorted({columns["subject"][i] for i in full_rows})
    wanted = available if not subjects else list(subjects)
    missing = [s for s in wanted if s not in available]
    if missing:
        raise InputError(
            f"{source_data.path}: no full-on rows of subjects {missing}; it has {', '.join(available[:20])}"
        )
    resolved_device = str(resolve_device(device))
    # An unknown subject is fitted on the device it is rendered on; a CUDA fit differs from a CPU one in
    # the last bits, so its avatar is not reused across the two.
    fit_device = {"device": "cuda"} if resolved_device.startswith("cuda") else {}
    tasks = []
    for subject in wanted:
        rows = [i for i in full_rows if columns["subject"][i] == subject]
        if splits:
            rows = [i for i in rows if columns["split"][i] in splits]
        if not rows:
            continue
        frames = sorted({int(columns["frame"][i]) for i in rows})
        frames = frames if all_frames else frames[:1]
        chosen = sorted(keys[i] for i in rows if int(columns["frame"][i]) in frames)
        qualified = f"{source_data.name}/{subject}"
        known = qualified in stage1_subjects
        tasks.append(
            ExpandTask(
                subject=subject,
                name=task_name(subject),
                source_keys=tuple(chosen),
                frames=tuple(frames),
                stage1_index=stage1_subjects.index(qualified) if known else None,
                split=columns["split"][rows[0]],
                fit_fingerprint=""
                if known
                else fingerprint_config(
                    {
                        "source_manifest_sha256": inputs["source_manifest_sha256"],
                        "stage1_checkpoint_sha256": inputs["stage1_checkpoint_sha256"],
                        "stage2_checkpoint_sha256": inputs["stage2_checkpoint_sha256"],
                        "subject": subject,
                        "frame": frames[0],
                        "fit_iterations": list(fit_iterations),
                        "fit_image_scale": fit_image_scale,
                        "seed": seed,
                        **fit_device,
                    }
                ),
            )
        )
    if not tasks:
        raise InputError(f"{source_data.path}: no subject has full-on rows in splits {splits}")
    names = [t.name for t in tasks]
    if len(set(names)) != len(names):
        raise InputError(f"{source_data.path}: subjects map to clashing part names {names}")

    parent = Path(parent)
    settings = ExpandSettings(
        source=source_data.path.resolve(),
        stage1=Path(stage1).resolve(),
        stage2=Path(stage2).resolve(),
        output=(parent / name).resolve(),
        avatars=(parent / f"{name}-avatars").resolve(),
        envmaps=tuple(p.resolve() for p in envmaps),
        fit_iterations=(int(fit_iterations[0]), int(fit_iterations[1])),
        fit_image_scale=float(fit_image_scale),
        all_frames=all_frames,
        device=resolved_device,
        seed=int(seed),
        lightings_per_pass=int(lightings_per_pass),
    )
    rig_patterns = [row["pattern"] for row in sorted(light_rows, key=lambda r: r["index"])]
    patterns = [*rig_patterns, "full", *(envmap_pattern(p) for p in envmaps)]
    if len(set(patterns)) != len(patterns):
        raise InputError(f"pattern names are not unique: {patterns}; rename the environment map files")
    config = {
        **inputs,
        "tasks": [asdict(t) for t in tasks],
        "fit_iterations": list(settings.fit_iterations),
        "fit_image_scale": settings.fit_image_scale,
        "device": "cuda" if settings.device.startswith("cuda") else "cpu",
        "seed": settings.seed,
        "patterns": patterns,
    }
    origin = dataset_provenance(source_data, settings, inputs)
    info = DatasetInfo(
        name=name,
        kind="synthetic-olat",
        template_mesh_id=source_data.manifest.info.template_mesh_id,
        lighting=(
            f"synthetic: {len(rig_patterns)}-light OLAT rig of {olat_dir.name} + full-on"
            + (f" + {len(envmaps)} environment maps" if envmaps else "")
        ),
        provenance=origin,
        config_fingerprint=fingerprint_config(config),
    )
    return ExpansionPlan(info, settings, tasks, light_rows, patterns, inputs)


def expand_dataset(
    plan: ExpansionPlan, workers: int = 1, executor: str = "local", progress: bool = True
) -> dict:
    """Run a plan: up-to-date check, tasks (skipping finished parts), lights, commit.

    Returns a report: output, manifest counts, per-task results, whether it was already up to date.
    """

    output = plan.settings.output
    if (output / MANIFEST_NAME).is_file():
        try:
            existing = load_manifest(output)
        except Exception:  # a corrupt manifest is rewritten below
            existing = None
        if existing is not None and existing.info.config_fingerprint == plan.info.config_fingerprint:
            return {"output": str(output), "up_to_date": True, "counts": existing.counts, "tasks": []}
    start = time.perf_counter()
    writer = ShardWriter(output, plan.info)
    writer.begin()
    pending = [t for t in plan.tasks if not writer.has_part(t.name)]
    results = run_expand_tasks(
        writer, plan.settings, pending, len(plan.patterns), workers, executor, progress
    )
    writer.write_lights([_light_row(row) for row in plan.light_rows])
    manifest: Manifest = writer.commit(progress=progress)
    return {
        "output": str(output),
        "up_to_date": False,
        "counts": manifest.counts,
        "skipped_tasks": [t.name for t in plan.tasks if t not in pending],
        "tasks": results,
        "seconds": time.perf_counter() - start,
    }


def run_expand_tasks(
    writer: ShardWriter,
    settings: ExpandSettings,
    tasks: list[ExpandTask],
    images_per_view: int,
    workers: int = 1,
    executor: str = "local",
    progress: bool = True,
) -> list[dict]:
    """:func:`~relightanyone.pipelines.expand.task.run_expand_task` for every task; reports in task order.

    ``executor`` "local" runs in this process (one worker or one task; the progress bar counts relit
    images per camera) or in the kept process pool of ``workers`` processes; "ray" runs Ray tasks that
    each hold a CPU, and a GPU when rendering on CUDA. Elsewhere than in this process the bar counts the
    images of finished subjects. Subjects that need a fit take longest, so they start first. Each
    subject's part is published here as its task returns (a worker never publishes).
    """
    runner = Executor(executor, workers, preload=WORKER_PRELOAD)
    total = sum(len(t.source_keys) for t in tasks) * images_per_view
    bar = progress_bar(total=total, desc=f"expand {settings.output.name}", unit="image", disable=not progress)

    def done(task: ExpandTask) -> None:
        writer.publish(task.name)
        bar.update(len(task.source_keys) * images_per_view)

    try:
        if runner.in_process(len(tasks)):
            return runner.map(
                partial(run_expand_task, writer, settings, on_images=bar.update),
                tasks,
                on_done=lambda task: writer.publish(task.name),
            )
        return runner.map(
            partial(run_expand_task, writer, settings),
            tasks,
            on_done=done,
            cost=lambda task: (not task.known, len(task.source_keys)),
            resources=TaskResources(cpus=1, gpus=1 if settings.device.startswith("cuda") else 0),
        )
    finally:
        bar.close()


def _light_row(row: dict) -> LightRow:
    return LightRow(
        index=int(row["index"]),
        name=row["name"],
        position_m=tuple(row["position_m"]),
        intensity_rgb=tuple(row["intensity_rgb"]),
        pattern=row["pattern"],
        full_on_intensity_rgb=None
        if row.get("full_on_intensity_rgb") is None
        else tuple(row["full_on_intensity_rgb"]),
    )
