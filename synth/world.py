"""The synthetic world: every native dataset, its tracking export and the answers, from one seed.

``generate_world(out, preset, seed)`` writes::

    out/faceolat/ ava256/ stereo_rig/ nersemble/     native datasets (D1..D4)
    out/tracking/<dataset>/<subject>/                VHAP-style tracking export (synth.vhap)
    out/tracking/template/                           the tracker's topology: template.obj (UVs), neck_mask.txt
    out/splits/<native folder>.json                  published protocol: {subject: "train" | "val" | "test"}
    out/answers/                                     what ingest never reads and evaluation does
        template/                                    template.obj, neck_mask.txt, landmarks.json
        splits.json                                  {dataset: {subject: "train" | "val" | "test"}}
        answer_lights.json                           the D1-rig lights of the OLAT answers (canonical)
        envmaps/<name>.exr                           10x20 lat-long maps of the relit answers
        <dataset>/truth.json                         DatasetTruth (cameras, poses, colour casts, lights ...)
        <dataset>/subjects/<subject>/                shape.obj, albedo.exr, specular_intensity.exr, roughness.exr
        <dataset>/olat/<subject>/<camera>/<k:03d>.exr       held-out (val, test) subjects under answer light k
        <dataset>/relit/<subject>/<camera>/<envmap>.exr     the same relit by each environment map
    out/world.json                                   written last: preset, seed, datasets, paths

Every random choice comes from ``np.random.default_rng`` seeded by (world seed, dataset index, purpose),
so the same seed and preset give the same bytes, whichever subset of datasets is generated.
"""

from __future__ import annotations

import importlib
import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from relightanyone.synth.d1_faceolat import d1_rig_lights
from relightanyone.synth.envmap import olat_relight_weights, procedural_envmaps, write_exr
from relightanyone.synth.errors import WorldError
from relightanyone.synth.presets import Preset, get_preset
from relightanyone.synth.raytrace import PointLights, Scene, SynthCamera, render
from relightanyone.synth.subject import make_subject
from relightanyone.synth.template import HeadTemplate, make_template, write_obj, write_template
from relightanyone.synth.truth import DatasetTruth
from relightanyone.synth.vhap import export_tracking

DATASET_MODULES = {"d1": "d1_faceolat", "d2": "d2_ava256", "d3": "d3_stereo_rig", "d4": "d4_nersemble"}
NATIVE_DIRS = {"d1": "faceolat", "d2": "ava256", "d3": "stereo_rig", "d4": "nersemble"}
WORLD_FORMAT_VERSION = 1
# Purposes mixed into the seeds, so that adding a consumer never shifts another one's random stream.
_NATIVE, _SUBJECTS, _TRACKING, _NAMES = 0, 1, 2, 3


def dataset_module(dataset: str):
    return importlib.import_module(f".{DATASET_MODULES[dataset]}", __package__)


def resolve_preset(preset: str | Preset) -> Preset:
    return preset if isinstance(preset, Preset) else get_preset(preset)


def _require_at_least(where: str, name: str, value: int, minimum: int) -> None:
    if value < minimum:
        raise ValueError(f"{where}: {name} must be >= {minimum}, got {value}")


def check_parameters(preset: Preset, datasets: tuple[str, ...]) -> None:
    """Raise ValueError naming the first impossible setting for the requested datasets."""
    if not datasets:
        raise ValueError("no dataset requested; pass at least one of d1, d2, d3, d4")
    for dataset in datasets:
        if dataset not in DATASET_MODULES:
            raise ValueError(f"unknown dataset {dataset!r}; expected some of {', '.join(DATASET_MODULES)}")
    if len(set(datasets)) != len(datasets):
        raise ValueError(f"dataset listed twice in {', '.join(datasets)}")
    for name, minimum in (("template_segments", 8), ("texture_size", 4), ("supersampling", 1)):
        _require_at_least(f"preset {preset.name}", name, getattr(preset, name), minimum)
    if not 1 <= preset.answer_lights <= preset.d1.lights:
        raise ValueError(
            f"preset {preset.name}: answer_lights must be in 1..d1.lights ({preset.d1.lights}), got {preset.answer_lights}"
        )
    _require_at_least(f"preset {preset.name}", "envmap_count", preset.envmap_count, 0)
    for dataset in datasets:
        size = preset.size_of(dataset)
        width, height = size.image_size
        where = f"preset {preset.name}, {dataset}"
        if size.cameras < 1:
            raise ValueError(f"{where}: needs at least one camera, got {size.cameras}")
        if width < 8 or height < 8:
            raise ValueError(f"{where}: image_size must be at least 8x8 pixels, got {width}x{height}")
        if min(size.train_subjects, size.val_subjects, size.test_subjects) < 0 or size.subjects < 1:
            raise ValueError(
                f"{where}: needs at least one subject, got {size.train_subjects} train + "
                f"{size.val_subjects} val + {size.test_subjects} test"
            )
        _require_at_least(where, "frames", size.frames, 1)
        if size.lights < 1:
            raise ValueError(f"{where}: needs at least one light, got {size.lights}")
    if "d3" in datasets and (preset.d3.image_size[0] % 2 or preset.d3.image_size[1] % 2):
        raise ValueError(
            f"preset {preset.name}, d3: Bayer images need even width and height, got {preset.d3.image_size}"
        )


def prepare_output(out: Path, overwrite: bool) -> None:
    """Refuse a non-empty folder unless ``overwrite``; overwrite only removes what looks like a world."""
    if out.exists() and not out.is_dir():
        raise WorldError(f"{out} exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise WorldError(
                f"{out} is not empty; pass --overwrite to replace the world in it, or choose another --out"
            )
        known = {*NATIVE_DIRS.values(), "tracking", "splits", "answers", "world.json"}
        strangers = sorted(p.name for p in out.iterdir() if p.name not in known)
        if strangers:
            raise WorldError(
                f"{out} holds files that are not part of a synthetic world ({', '.join(strangers[:5])}); "
                "refusing to overwrite it, choose another --out"
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def make_subjects(preset: Preset, template: HeadTemplate, dataset: str, seed: int):
    """The dataset's people (train first, then validation, then test) and their splits."""
    index = list(DATASET_MODULES).index(dataset)
    size = preset.size_of(dataset)
    count = size.subjects
    module = dataset_module(dataset)
    names_rng = np.random.default_rng([seed, index, _NAMES])
    names = (
        module.subject_names(names_rng, count)
        if hasattr(module, "subject_names")
        else [f"{k + 1:03d}" for k in range(count)]
    )
    seeds = np.random.SeedSequence([seed, index, _SUBJECTS]).generate_state(count, dtype=np.uint64)
    subjects = [
        make_subject(template, name, int(s % (2**63)), preset.texture_size)
        for name, s in zip(names, seeds, strict=True)
    ]
    return subjects, dict(zip(names, subject_splits(size), strict=True))


def subject_splits(size) -> list[str]:
    """The split of each of a dataset's subjects, in their order: train, then val, then test."""
    return ["train"] * size.train_subjects + ["val"] * size.val_subjects + ["test"] * size.test_subjects


def answer_lights(preset: Preset) -> tuple[PointLights, np.ndarray]:
    """The ``preset.answer_lights`` lights of the D1 rig (evenly spread indices) and their rig indices.

    The rig is the one D1's generator uses (its own fixed seed), so answers and D1 share their lights.
    """

    rig = d1_rig_lights(preset)
    indices = np.unique(np.round(np.linspace(0, len(rig) - 1, preset.answer_lights)).astype(np.int64))
    return rig.subset(indices), indices


def truth_camera(camera) -> SynthCamera:
    return SynthCamera(
        camera.name,
        np.asarray(camera.K),
        np.asarray(camera.w2c),
        int(camera.width),
        int(camera.height),
        np.asarray(camera.dist),
    )


def write_subject_answers(folder: Path, template: HeadTemplate, subject) -> None:
    """True shape (OBJ, canonical) and appearance maps (EXR; scalar maps as grey RGB) of one subject."""
    write_obj(folder / "shape.obj", subject.vertices, template.faces, template.uvs, template.face_uvs)
    write_exr(folder / "albedo.exr", subject.albedo)
    for name in ("specular_intensity", "roughness"):
        values = np.asarray(getattr(subject, name), dtype=np.float32)
        write_exr(folder / f"{name}.exr", np.repeat(values[..., None], 3, axis=-1))


def olat_answer_images(preset: Preset, scene, camera, lights: PointLights) -> np.ndarray:
    """(L, H, W, 3) float32 true OLAT images of ``scene`` in a native ``camera``, one per answer light."""
    return render(
        scene, truth_camera(camera), lights, per_light=True, supersampling=preset.supersampling
    ).image


def render_subject_olat(
    world: Path, dataset: str, subject: str, cameras: list[str], preset: Preset | None = None
) -> dict[str, np.ndarray]:
    """True OLAT images of any subject of a generated world, rendered as the held-out answers are.

    Held-out subjects have theirs on disk (``answers/<dataset>/olat``); training subjects do not, and
    this regenerates them from the world's seed (the same people, textures and answer lights).
    ``preset``: the world's preset when it is not one of the named ones (world.json records the name).
    Returns camera -> (L, H, W, 3) float32 under the answer lights.
    """
    world = Path(world)
    description_path = world / "world.json"
    if not description_path.is_file():
        raise FileNotFoundError(
            f"{description_path}: not a generated world; its subjects cannot be re-rendered"
        )
    description = json.loads(description_path.read_text())
    if preset is None:
        try:
            preset = resolve_preset(description["preset"])
        except (KeyError, ValueError) as error:
            raise ValueError(f"{description_path}: {error}; pass the world's preset") from None
    template = make_template(preset.template_segments)
    people = {p.name: p for p in make_subjects(preset, template, dataset, int(description["seed"]))[0]}
    if subject not in people:
        raise ValueError(
            f"{world}: world dataset {dataset!r} has no subject {subject!r}; it has {sorted(people)}"
        )
    truth = DatasetTruth.load(world / "answers" / dataset / "truth.json")
    missing = [c for c in cameras if c not in truth.cameras]
    if missing:
        raise ValueError(f"{world}: world dataset {dataset!r} has no camera(s) {missing}")
    lights, _ = answer_lights(preset)
    scene = Scene.from_subject(template, people[subject])
    return {c: olat_answer_images(preset, scene, truth.cameras[c], lights) for c in cameras}


def write_relighting_answers(
    folder: Path,
    preset: Preset,
    template: HeadTemplate,
    subject,
    truth: DatasetTruth,
    lights: PointLights,
    envmaps: list[tuple[str, np.ndarray]],
    progress,
) -> None:
    """OLAT images of a held-out subject under every answer light from every camera, and env-map relights."""
    scene = Scene.from_subject(template, subject)
    weights = [
        (name, olat_relight_weights(env, lights.positions, lights.intensities)) for name, env in envmaps
    ]
    for camera in truth.cameras.values():
        olat = olat_answer_images(preset, scene, camera, lights)
        for k in range(len(olat)):
            write_exr(folder / "olat" / subject.name / camera.name / f"{k:03d}.exr", olat[k], half=True)
        for name, w in weights:
            relit = np.einsum("lc,lhwc->hwc", w, olat.astype(np.float64)).astype(np.float32)
            write_exr(folder / "relit" / subject.name / camera.name / f"{name}.exr", relit, half=True)
        if progress is not None:
            progress.update(1)


def expected_work(preset: Preset, datasets: tuple[str, ...]) -> int:
    """Render calls the world makes (for the progress bar)."""
    total = 0
    for dataset in datasets:
        module = dataset_module(dataset)
        size = preset.size_of(dataset)
        # One render per subject, frame and camera, unless the module counts its own (D3's chart frames).
        if hasattr(module, "expected_renders"):
            total += module.expected_renders(preset)
        else:
            total += size.subjects * size.cameras * size.frames
        total += size.held_out_subjects * size.cameras  # answers
    return total


def generate_dataset(out, preset, dataset, seed, template, lights, envmaps, progress) -> tuple[str, dict]:
    """One dataset: native files, tracking export, answers. Returns (dataset, its splits)."""
    index = list(DATASET_MODULES).index(dataset)
    subjects, splits = make_subjects(preset, template, dataset, seed)
    truth = dataset_module(dataset).generate(
        out, preset, template, subjects, splits, np.random.default_rng([seed, index, _NATIVE]), progress
    )
    tracking = export_tracking(
        out, truth, template, subjects, np.random.default_rng([seed, index, _TRACKING])
    )
    truth.extra["tracking_from_canonical"] = tracking
    truth.extra["tracking_dir"] = f"tracking/{dataset}"
    folder = out / "answers" / dataset
    for subject in subjects:
        write_subject_answers(folder / "subjects" / subject.name, template, subject)
        if splits[subject.name] != "train":
            write_relighting_answers(folder, preset, template, subject, truth, lights, envmaps, progress)
    truth.save(folder / "truth.json")
    return dataset, dict(sorted(splits.items()))


def job_cost(preset: Preset, dataset: str) -> float:
    """Rough relative cost of a dataset: pixels traced, counting renders and answer renders."""
    size = preset.size_of(dataset)
    width, height = size.image_size
    return float(expected_work(preset, (dataset,)) * width * height)


class _QueueProgress:
    """Progress sink of a worker process: forwards render counts to the parent's bar."""

    def __init__(self, queue):
        self.queue = queue

    def update(self, amount: int = 1) -> None:
        self.queue.put(int(amount))

    __call__ = update


def run_jobs(jobs: list[tuple], workers: int, bar) -> list[tuple[str, dict]]:
    """Run :func:`generate_dataset` for every job, in ``workers`` processes when more than one.

    Each dataset draws only from its own seeds, so the bytes do not depend on the number of workers.
    """
    if workers <= 1 or len(jobs) <= 1:
        results = []
        for job in jobs:
            if bar is not None:
                bar.set_description(f"synth {job[1].name} {job[2]}")
            results.append(generate_dataset(*job, bar))
        return results
    import multiprocessing
    import queue as queue_module
    from concurrent.futures import ProcessPoolExecutor

    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    context = multiprocessing.get_context(method)
    with (
        context.Manager() as manager,
        ProcessPoolExecutor(min(workers, len(jobs)), mp_context=context) as pool,
    ):
        counts = manager.Queue()
        # Largest datasets first, so that the small ones fill the gaps at the end.
        order = sorted(range(len(jobs)), key=lambda k: job_cost(jobs[k][1], jobs[k][2]), reverse=True)
        submitted = {k: pool.submit(generate_dataset, *jobs[k], _QueueProgress(counts)) for k in order}
        futures = [submitted[k] for k in range(len(jobs))]
        while not all(f.done() for f in futures):
            try:
                amount = counts.get(timeout=0.2)
            except queue_module.Empty:
                continue
            if bar is not None:
                bar.update(amount)
        while bar is not None and not counts.empty():
            bar.update(counts.get())
        return [f.result() for f in futures]


def generate_world(
    out: Path,
    preset: str | Preset,
    seed: int = 0,
    datasets=("d1", "d2", "d3", "d4"),
    progress: bool | Callable[..., Any] = True,
    overwrite: bool = False,
    workers: int = 1,
) -> dict:
    """Write a synthetic world into ``out``; returns the world description (also saved as world.json).

    preset: "tiny", "demo", "paper" or a :class:`Preset`; datasets: any of d1..d4, in any order.
    workers: processes generating datasets side by side (the bytes do not depend on it).
    progress: a tqdm bar when True, none when False, or the function that makes the progress report
        (called like ``tqdm(total=..., desc=..., unit=...)``; the command line passes its own).
    Raises ValueError for unknown datasets or impossible sizes, ``WorldError`` for a non-empty ``out``
    without ``overwrite``.
    """
    preset = resolve_preset(preset)
    requested = tuple(datasets)
    check_parameters(preset, requested)
    datasets = tuple(d for d in DATASET_MODULES if d in requested)  # a fixed order, whatever was asked
    out = Path(out)
    prepare_output(out, overwrite)

    bar = None
    if progress:
        from tqdm import tqdm

        make_bar = progress if callable(progress) else tqdm
        bar = make_bar(total=expected_work(preset, datasets), desc=f"synth {preset.name}", unit="render")
    try:
        template = make_template(preset.template_segments)
        answers = out / "answers"
        write_template(answers / "template", template)
        # A tracker ships its topology (FLAME's head template with UVs); ingest reads it from here.
        write_template(out / "tracking" / "template", template)
        lights, light_indices = answer_lights(preset)
        envmaps = procedural_envmaps(preset.envmap_count, seed) if preset.envmap_count else []
        for name, env in envmaps:
            write_exr(answers / "envmaps" / f"{name}.exr", env)
        (answers / "answer_lights.json").write_text(
            json.dumps(
                {
                    "rig": "d1",
                    "rig_indices": light_indices.tolist(),
                    "positions": lights.positions.tolist(),
                    "intensities": lights.intensities.tolist(),
                    "space": "canonical head space, metres; intensities linear RGB (render units)",
                },
                indent=1,
            )
        )

        jobs = [(out, preset, dataset, seed, template, lights, envmaps) for dataset in datasets]
        all_splits = dict(run_jobs(jobs, workers, bar))
        (answers / "splits.json").write_text(json.dumps(all_splits, indent=1, sort_keys=True))
        # The published evaluation protocol (as real benchmarks publish their held-out subjects):
        # which subjects train, which select models (val) and which are held out for the test, and
        # nothing about them. Ingest reads it (`--splits`) and writes each row's split from it.
        for dataset, splits in all_splits.items():
            protocol = out / "splits" / f"{NATIVE_DIRS[dataset]}.json"
            protocol.parent.mkdir(parents=True, exist_ok=True)
            protocol.write_text(json.dumps(splits, indent=1, sort_keys=True))
    finally:
        if bar is not None:
            bar.close()

    world = {
        "format_version": WORLD_FORMAT_VERSION,
        "preset": preset.name,
        "seed": int(seed),
        "datasets": list(datasets),
        "native_dirs": {d: NATIVE_DIRS[d] for d in datasets},
        "tracking_dir": "tracking",
        "answers_dir": "answers",
        "envmaps": [name for name, _ in envmaps],
    }
    (out / "world.json").write_text(json.dumps(world, indent=1))
    return world
