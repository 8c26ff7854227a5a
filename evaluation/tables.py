"""The evaluation tables: fits of held-out subjects, relit and compared with the truth.

* **Table 1** (OLAT relighting, paper Table 1 analogue): each test subject of the OLAT dataset is fitted on
  its full-on frame (multi-view) with the two-stage model and with the single-stage baseline; both are
  relit under rig lights and compared with the subject's OLAT images.
* **Table 2** (environment maps, paper Table 2 analogue): the same subjects, fitted from one image (the
  most frontal camera) and from all views, relit by the world's environment maps; the truth is the world's
  image-based relighting of its true OLAT images, and the model's OLAT renders are combined the same way.
* **Table 3** (lighting-code ablation, not measurable in the paper): flat-lit test subjects fitted on
  their full-on frame with the OLAT dataset's lighting code z_l (the method) and with their own dataset's
  z_l (no lighting alignment), compared with their true OLAT images.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from relightanyone.errors import InputError
from relightanyone.evaluation.ablation import (
    arm_dataset,
    arm_subject_index,
    budgets_agree,
    load_arms,
    single_run_budget,
)
from relightanyone.evaluation.baseline_choice import (
    choose_baseline,
    require_validation,
    validation_subjects,
)
from relightanyone.evaluation.cases import (
    EvalView,
    LightCase,
    answer_envmap_cases,
    answer_frame,
    answer_masks,
    answer_olat_cases,
    callable_olat_cases,
    expected_olat_over_full_on,
    has_olat_rows,
    olat_sum_over_full_on,
    row_olat_cases,
    stack_truth,
    view_cameras,
)
from relightanyone.evaluation.metrics import LpipsMetric, image_metrics, lpips_status
from relightanyone.evaluation.single_image import monocular_views
from relightanyone.evaluation.single_stage import SingleStageFitter, load_single_stage_run
from relightanyone.evaluation.splits import refuse_trained_subjects, runs_that_trained, training_runs
from relightanyone.evaluation.truth import WorldAnswers
from relightanyone.evaluation.unknown_lighting import (
    select_views,
    subject_input_lighting,
    unknown_lighting_views,
)
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import make_mesh_key
from relightanyone.format.torch_dataset import NormalizedTorchDataset, image_hwc
from relightanyone.model.fit.avatar import check_pinhole_cameras, decoded_avatar, relight_views
from relightanyone.model.fit.fitter import FitSettings, load_relightable_model, make_fitter
from relightanyone.model.fit.views import FitViews, load_fit_views
from relightanyone.model.train.budget import two_stage_budget
from relightanyone.model.train.run_files import read_run_info
from relightanyone.render.lights import PointLights

# true_image(dataset, subject, camera, light) -> (image (H, W, 3), mask (H, W)) in the row's geometry.
TrueOlatImage = Callable[[str, str, str, int], tuple[np.ndarray, np.ndarray]]
UNIT_TOLERANCE = 1.25  # answers are rescaled only when their unit differs from the rows' by more


@dataclass
class EvaluationSettings:
    """Budget and limits of an evaluation run."""

    inversion_iterations: int = 100
    finetune_iterations: int = 100
    max_views: int | None = 8  # cameras per fit and per comparison, evenly spread over the rig
    lights_subset: int | None = 16  # OLAT lights compared (evenly spread rig indices)
    envmaps: int | None = None  # environment maps compared (all when None)
    subjects_per_dataset: int | None = 1  # held-out subjects per dataset (all when None)
    ablation_fits: bool = True  # Table 3b fits held-out flat-lit subjects with every ablation arm
    unknown_lighting: bool = True  # Table 1/2 inputs under the world's unknown lighting (else the rows)
    # Table 3b fits a flat-lit subject under its dataset's lighting code (else as an unknown rig lighting)
    flat_fits_with_dataset_code: bool = True
    monocular_single_image: bool = True  # Table 2's single image: monocular mesh, own mask, generic focal
    split: str = "test"  # the held-out split scored: "test" (reported numbers) or "val" (model selection)
    views_per_step: int = 4
    lighting_prior_weight: float = FitSettings.lighting_prior_weight  # λ_I of every fit
    seed: int = 0
    progress: bool = True
    device: str = "cpu"  # torch device of the fits and renders; scores are computed on the CPU


@dataclass
class EvaluationInputs:
    """What is evaluated: normalized datasets keyed by their world dataset name (d1..d4), the runs, and
    the truth (a synthetic world's answers, and/or an analytic OLAT truth)."""

    datasets: dict[str, Path]
    stage1: Path
    stage2: Path
    single_stage: Path | None = None
    # Further single-stage runs (other loss variants): the baseline is the best on validation subjects.
    single_stage_variants: tuple[Path, ...] = ()
    answers: WorldAnswers | None = None
    # Lighting-code ablation arms: arm name (``with-zl``, ``no-zl``, ``colour-matrix``) -> (stage 1, stage 2)
    ablation: dict[str, tuple[Path, Path]] = field(default_factory=dict)
    true_olat_image: TrueOlatImage | None = None


def other_training_runs(inputs: EvaluationInputs) -> dict[str, Path]:
    """The ablation arms' runs and the single-stage candidates, labelled, for the split check."""
    runs = {f"single-stage candidate {i + 1}": Path(p) for i, p in enumerate(inputs.single_stage_variants)}
    for arm, (stage1, stage2) in inputs.ablation.items():
        runs |= {f"{arm} stage 1": Path(stage1), f"{arm} stage 2": Path(stage2)}
    return runs


@dataclass
class Comparison:
    """Per-image metrics of one method on a set of cases, with one example row for the image grid."""

    scores: dict[str, list[float]] = field(default_factory=dict)
    examples: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)

    def add(
        self, label: str, prediction: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor, lpips
    ) -> None:
        prediction = prediction.cpu()  # renders come from the fit's device; the truth is on the CPU
        for name, values in image_metrics(prediction, truth, mask, lpips).items():
            self.scores.setdefault(name, []).extend(float(v) for v in values)
        self.examples.append((label, prediction[0].numpy(), truth[0].numpy(), mask[0, 0].numpy()))

    def summary(self) -> dict[str, float]:
        return {name: float(np.mean(values)) for name, values in self.scores.items()} | {
            "images": len(next(iter(self.scores.values()), []))
        }


def evenly_spread(count: int, limit: int | None) -> list[int]:
    """``limit`` indices spread evenly over range(count) (all of them when limit is None or larger)."""
    if limit is None or limit >= count:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, max(1, limit))})


def subject_cameras(dataset_dir: Path, subject: str, limit: int | None) -> tuple[list[str], str]:
    """(cameras of the first full-on frame, evenly limited; the most frontal of them: centre nearest +z)."""

    rows = NormalizedTorchDataset(dataset_dir, subjects=subject, patterns="full")
    if not len(rows):
        raise InputError(f"{rows.source.path}: subject {subject!r} has no full-on rows to fit")
    by_camera = sorted(first_frame_rows(rows).items(), key=lambda entry: entry[1])
    chosen = [rows.row(by_camera[i][0]) for i in evenly_spread(len(by_camera), limit)]

    def frontality(row) -> float:
        centre = -row.w2c[:3, :3].T @ row.w2c[:3, 3]
        return float(centre[2] / max(np.linalg.norm(centre), 1e-9))

    return [r.camera for r in chosen], max(chosen, key=frontality).camera


def first_frame_rows(rows: NormalizedTorchDataset) -> dict[int, str]:
    """Item index -> camera of the rows of the first frame in ``rows`` (from the index, nothing decoded)."""
    frames, cameras = rows.column("frame"), rows.column("camera")
    first = min(frames)
    return {
        i: camera for i, (frame, camera) in enumerate(zip(frames, cameras, strict=True)) if frame == first
    }


def test_subjects(
    inputs: EvaluationInputs, world_name: str, limit: int | None, split: str = "test"
) -> list[str]:
    """Held-out subjects of ``split``: the world's splits when answers are given, else the rows' split."""

    dataset = NormalizedDataset(inputs.datasets[world_name])
    if inputs.answers is not None and world_name in inputs.answers.splits:
        names = [s for s in inputs.answers.subjects_in(world_name, split) if s in dataset.subjects]
    else:
        names = sorted(set(NormalizedTorchDataset(dataset, splits=split).column("subject")))
    return names if limit is None else names[:limit]


@torch.no_grad()
def render_point_lights(avatar, cameras, lights: PointLights) -> torch.Tensor:
    """The avatar under each of L point lights alone -> (L, V, 3, H, W), in one splat per view.

    Works for any avatar :func:`relightanyone.model.fit.avatar.relight_views` accepts (the fitted two-stage
    avatar and the single-stage one): the reflectance is decoded once per view and the L relit colours are
    splatted as 3L feature channels.
    """
    singles = [
        PointLights(lights.positions[k : k + 1], lights.intensities[k : k + 1]) for k in range(len(lights))
    ]
    return render_lightings(avatar, cameras, singles)


def render_lightings(avatar, cameras, lightings: list[PointLights]) -> torch.Tensor:
    """The avatar in ``cameras`` under each of P light sets -> (P, V, 3, H, W), all in one pass."""

    width, height = check_pinhole_cameras(cameras)
    return relight_views(
        avatar,
        cameras.w2c.float(),
        cameras.K.float(),
        width,
        height,
        lightings,
        lightings_per_pass=len(lightings),
    )


@torch.no_grad()
def render_weighted_rig(avatar, cameras, cases: list[LightCase]) -> torch.Tensor:
    """The avatar under each case's weighted rig, every light on at once -> (E, V, 3, H, W).

    A case's lighting is its basis lights with intensities scaled by its per-channel weights: the
    environment as the light stage discretizes it, which is also how the truth was relit. The model
    shades it in one pass, as RGCA shades an environment. Summing its single-light renders instead would
    not be the model's prediction: its shading clamps negative diffuse per render, so the negative lobes
    its low-order transfer gives lights behind the head, which cancel in a joint render, would each be
    clamped to zero and the sum would come out too bright.
    """
    lightings = []
    for case in cases:
        weights = torch.as_tensor(case.weights, dtype=torch.float32, device=case.basis.intensities.device)
        weighted = PointLights(case.basis.positions, case.basis.intensities.float() * weights)
        lightings.append(weighted.to(cameras.w2c.device))
    return render_lightings(avatar, cameras, lightings)


def compare(avatar, cases: list[LightCase], lpips) -> Comparison:
    """Render every case (grouped by camera set: one batched render per group, on the avatar's device)
    and score it."""
    device = avatar.means.device
    comparison = Comparison()
    groups: dict[tuple[str, ...], list[LightCase]] = {}
    for case in cases:
        groups.setdefault(tuple(v.camera for v in case.views), []).append(case)
    predictions: dict[int, torch.Tensor] = {}
    for group in groups.values():
        cameras = view_cameras(group[0].views).to(device)
        olat = [c for c in group if c.light is not None]
        if olat:
            lights = PointLights(
                torch.cat([c.light.positions for c in olat]), torch.cat([c.light.intensities for c in olat])
            ).to(device)
            for case, image in zip(olat, render_point_lights(avatar, cameras, lights), strict=True):
                predictions[id(case)] = image
        relit = [c for c in group if c.light is None]
        if relit:
            for case, image in zip(relit, render_weighted_rig(avatar, cameras, relit), strict=True):
                predictions[id(case)] = image
    for case in cases:
        truth, mask = stack_truth(case.views)
        comparison.add(case.label, predictions[id(case)], truth, mask, lpips)
    return comparison


class Evaluation:
    """Runs the three tables; ``results`` is the JSON-ready summary, ``grids`` the example images."""

    def __init__(self, inputs: EvaluationInputs, settings: EvaluationSettings) -> None:

        self.inputs = inputs
        self.settings = settings
        self.training_runs = training_runs(
            inputs.stage1,
            inputs.stage2,
            inputs.single_stage,
            list(inputs.datasets.values()),
            other_training_runs(inputs),
        )
        held_out = [
            f"{NormalizedDataset(path).name}/{subject}"
            for world_name, path in sorted(inputs.datasets.items())
            for subject in self.held_out_subjects(world_name)
        ]
        refuse_trained_subjects(settings.split, held_out, self.training_runs)
        if not held_out:
            raise InputError(
                f"no {settings.split} subjects in the evaluated datasets {sorted(inputs.datasets)}; "
                f"the world's or the rows' splits give none (choose another --split)"
            )
        self.device = torch.device(settings.device)
        self.model = load_relightable_model(inputs.stage1, inputs.stage2, self.device)
        self.arms = load_arms(inputs.ablation, self.model, inputs.stage1, inputs.stage2, self.device)
        available, reason = lpips_status()
        self.lpips = LpipsMetric() if available else None
        self.lpips_note = reason
        self.olat_world = self._olat_world_name()
        rig_size = len(self.model.rig)
        self.light_indices = evenly_spread(rig_size, settings.lights_subset)
        self.results: dict = {"lpips": reason, "timings_s": {}, "units": {}}
        self.grids: dict[str, list] = {}
        self.input_lightings: dict[str, dict] = {}
        self.inputs_images: dict[str, np.ndarray] = {}
        self.single = None
        candidates = [c for c in (inputs.single_stage, *inputs.single_stage_variants) if c is not None]
        if len(candidates) > 1:
            self.single, chosen, self.results["baseline_choice"] = self.choose_single_stage(candidates)
            self.inputs = dataclasses.replace(inputs, single_stage=chosen, single_stage_variants=())
        elif candidates:
            self.single = load_single_stage_run(candidates[0], self.device)
        self.budgets = self._budgets()

    def choose_single_stage(self, candidates: list[Path]):
        """(run, its folder, the record of the choice): the single-stage candidate with the best OLAT
        relighting on the OLAT dataset's validation subjects (:mod:`relightanyone.evaluation.baseline_choice`)."""
        path = self.inputs.datasets[self.olat_world]
        subjects = validation_subjects(path, self.inputs.answers, self.olat_world)
        require_validation(subjects, path, len(candidates))
        runs = {str(c): load_single_stage_run(c, self.device) for c in candidates}
        scores: dict[str, list[float]] = {str(c): [] for c in candidates}
        for subject in subjects:
            cameras, _ = subject_cameras(path, subject, self.settings.max_views)
            cases = row_olat_cases(path, subject, self.model.rig, self.light_indices, cameras)
            if not cases:
                raise InputError(
                    f"{path}: validation subject {subject!r} has no OLAT rows to score the baseline on"
                )
            for candidate in candidates:
                label = f"single-stage validation, {Path(candidate).name}"
                avatar = self.fit(self.olat_world, subject, cameras, label, single_run=runs[str(candidate)])
                scores[str(candidate)] += compare(avatar, cases, None).scores["psnr"]
        best, record = choose_baseline(candidates, scores)
        return runs[str(best)], Path(best), record | {"subjects": subjects}

    def _budgets(self) -> dict[str, dict]:
        """Training budget of the model behind every table row (row name -> budget)."""
        two_stage = two_stage_budget(self.inputs.stage1, self.inputs.stage2)
        budgets = {"two_stage": two_stage, "multi_view": two_stage, "single_image": two_stage}
        if self.inputs.single_stage is not None:
            budgets["single_stage"] = single_run_budget(self.inputs.single_stage)
        budgets.update({row: arm.budget for row, arm in self.arms.items()})
        return budgets

    def _olat_world_name(self) -> str:

        for world_name, path in self.inputs.datasets.items():
            if NormalizedDataset(path).name == self.model.olat_dataset:
                return world_name
        raise InputError(
            f"stage-2 run {self.inputs.stage2} was trained on dataset {self.model.olat_dataset!r}, which is "
            f"not among the evaluated datasets {sorted(self.inputs.datasets)}; pass it with --data"
        )

    # -- fitting ---------------------------------------------------------------------------------------
    def fit_settings(self):

        return FitSettings(
            inversion_iterations=self.settings.inversion_iterations,
            finetune_iterations=self.settings.finetune_iterations,
            views_per_step=self.settings.views_per_step,
            lighting_prior_weight=self.settings.lighting_prior_weight,
            seed=self.settings.seed,
            progress=self.settings.progress,
        )

    def fit(
        self,
        world_name: str,
        subject: str,
        cameras: list[str],
        label: str,
        model=None,
        single=False,
        data: Path | None = None,
        views: FitViews | None = None,
        single_run=None,
        input_dataset: str | None = None,
    ):
        """Fit ``views``, by default the subject's full-on frame in ``cameras`` (read from ``data``, default
        the evaluated dataset); returns the avatar (timed under ``label``). With ``input_dataset``, the
        views are rendered under that stage-1 dataset's lighting code (:class:`DatasetLitFitter`)."""

        if views is None:
            views = load_fit_views(data or self.inputs.datasets[world_name], subject, cameras=cameras)
        self.inputs_images.setdefault(f"{world_name}/{subject}", views.images[0].permute(1, 2, 0).numpy())
        views = views.to(self.device)
        torch.manual_seed(self.settings.seed)
        start = time.perf_counter()
        if single or single_run is not None:
            fitter = SingleStageFitter(single_run or self.single, views, self.fit_settings())
        else:
            fitter = make_fitter(model or self.model, views, self.fit_settings(), input_dataset)
        fitter.invert()
        fitter.finetune()
        avatar = fitter.avatar()
        self.results["timings_s"][f"{world_name}/{subject} {label}"] = round(time.perf_counter() - start, 2)
        return avatar

    # -- truth -----------------------------------------------------------------------------------------
    def olat_cases(self, world_name: str, subject: str, cameras: list[str]) -> tuple[list[LightCase], str]:
        """OLAT ground truth of a subject and where it came from."""
        data = self.inputs.datasets[world_name]
        rig = self.model.rig
        if has_olat_rows(data, subject):
            return row_olat_cases(data, subject, rig, self.light_indices, cameras), "normalized OLAT rows"
        if self.inputs.true_olat_image is not None:
            rows = self._row_views(world_name, subject, cameras)
            truth = lambda camera, light: self.inputs.true_olat_image(world_name, subject, camera, light)  # noqa: E731
            return callable_olat_cases(truth, rows, rig, self.light_indices), "analytic OLAT truth"
        if self.inputs.answers is not None:
            frame = answer_frame(self.inputs.answers, world_name, data, subject, cameras)
            masks = answer_masks(self.inputs.answers, frame)
            cases = answer_olat_cases(self.inputs.answers, frame, rig, self.light_indices, masks)
            scale = self.results["units"].get("answer_scale")
            if scale is not None:
                for case in cases:
                    for view in case.views:
                        view.image = view.image * np.asarray(scale, dtype=np.float32)
            return cases, "world answers (warped into the row crops)"
        raise InputError(f"no OLAT truth for {world_name}/{subject}: pass the world (--world)")

    def _row_views(self, world_name: str, subject: str, cameras: list[str]) -> list[EvalView]:

        rows = NormalizedTorchDataset(self.inputs.datasets[world_name], subjects=subject, patterns="full")
        by_camera = {camera: rows.row(i) for i, camera in first_frame_rows(rows).items()}
        return [
            EvalView(c, by_camera[c].K, by_camera[c].w2c, by_camera[c].width, by_camera[c].height, None, None)
            for c in cameras
        ]

    def check_units(
        self, world_name: str, subject: str, cameras: list[str], row_cases: list[LightCase]
    ) -> None:
        """Compare the subject's OLAT rows with the answers of the same lights: one ratio per channel."""
        answers = self.inputs.answers
        if answers is None or world_name not in answers.splits or not row_cases:
            return
        frame = answer_frame(answers, world_name, self.inputs.datasets[world_name], subject, cameras)
        masks = answer_masks(answers, frame)
        answer_cases = {
            c.label: c for c in answer_olat_cases(answers, frame, self.model.rig, self.light_indices, masks)
        }
        rows_total, answer_total = np.zeros(3), np.zeros(3)
        for case in row_cases:
            if case.label in answer_cases:
                rows_total += sum(v.image.sum(axis=(0, 1)) for v in case.views)
                answer_total += sum(v.image.sum(axis=(0, 1)) for v in answer_cases[case.label].views)
        if not answer_total.all():
            return
        ratio = rows_total / answer_total
        agree = bool(np.all((ratio < UNIT_TOLERANCE) & (ratio > 1 / UNIT_TOLERANCE)))
        self.results["units"] = {
            "rows_over_answers": ratio.round(4).tolist(),
            "subject": f"{world_name}/{subject}",
            "agree": agree,
            "note": "answer OLAT images and the OLAT rows share one unit; answers are used as they are"
            if agree
            else "answers were rescaled by rows_over_answers to the model's unit",
        }
        if not agree:
            self.results["units"]["answer_scale"] = ratio.tolist()

    # -- tables ----------------------------------------------------------------------------------------
    def table1_and_2(self) -> None:
        world_name = self.olat_world
        table1, table2 = {}, {}
        for subject in self.held_out_subjects(world_name):
            key = f"{world_name}/{subject}"
            cameras, frontal = subject_cameras(
                self.inputs.datasets[world_name], subject, self.settings.max_views
            )
            cases, source = self.olat_cases(world_name, subject, cameras)
            if source == "normalized OLAT rows":
                self.check_units(world_name, subject, cameras, cases)
                ratio = olat_sum_over_full_on(self.inputs.datasets[world_name], subject, cameras[:2])
                self.results["units"]["olat_sum_over_full_on"] = ratio
                self.results["units"]["expected_from_lights"] = expected_olat_over_full_on(
                    self.inputs.datasets[world_name]
                )
            inputs = self.held_out_input(world_name, subject, cameras)
            ours = self.fit(world_name, subject, cameras, "two-stage multi-view", views=inputs)
            rows = {"two_stage": compare(ours, cases, self.lpips)}
            if self.single is not None:
                baseline = self.fit(
                    world_name, subject, cameras, "single-stage multi-view", single=True, views=inputs
                )
                rows["single_stage"] = compare(baseline, cases, self.lpips)
            table1[key] = {
                "source": source,
                "input": self.input_description(inputs),
                "cameras": cameras,
                "lights": [c.label for c in cases],
                "seen_in_training": self.seen_in_training(world_name, subject),
                "rows": rows,
            }
            table2_entry = self.table2_subject(world_name, subject, cameras, frontal, ours, inputs)
            if table2_entry is not None:
                table2[key] = table2_entry
        self.tables = {"table1": table1, "table2": table2}

    def held_out_input(self, world_name: str, subject: str, cameras: list[str]) -> FitViews | None:
        """The fit input of a Table 1/2 subject under the world's unknown lighting
        (:mod:`relightanyone.evaluation.unknown_lighting`); None (the dataset's full-on rows) when
        ``settings.unknown_lighting`` is off or the world has no answers for the dataset."""
        answers = self.inputs.answers
        if not self.settings.unknown_lighting or answers is None or world_name not in answers.splits:
            return None
        path = self.inputs.datasets[world_name]
        dataset = NormalizedDataset(path)
        frame = answer_frame(answers, world_name, path, subject, cameras)
        lighting = subject_input_lighting(answers, world_name, subject)
        tracked = dataset.meshes().get(make_mesh_key(subject, frame.frame))
        tracked = None if tracked is None else torch.as_tensor(np.asarray(tracked), dtype=torch.float32)
        views = unknown_lighting_views(
            answers,
            frame,
            lighting,
            answer_masks(answers, frame),
            dataset.name,
            tracked,
            self.results["units"].get("answer_scale"),
        )
        self.input_lightings[f"{world_name}/{subject}"] = lighting.describe()
        return views

    def input_description(self, views: FitViews | None) -> dict:
        """What a fit was given: the input lighting and the lighting prior it started from."""
        if views is None:
            return {"images": "the dataset's full-on rows", "lighting": "the calibrated full-on rig"}
        return {
            "images": "the world's render under a lighting unknown to the fit",
            "lighting": self.input_lightings.get(f"{self.olat_world}/{views.subject}"),
            "prior": "the full-on rig of the OLAT dataset's training captures (lights.arrow)",
        }

    def table2_subject(self, world_name, subject, cameras, frontal, multi_view_avatar, inputs=None):
        answers = self.inputs.answers
        if answers is None or world_name not in answers.splits or not answers.envmap_names():
            return None
        envmaps = answers.envmap_names()
        envmaps = [envmaps[i] for i in evenly_spread(len(envmaps), self.settings.envmaps)]
        frame = answer_frame(answers, world_name, self.inputs.datasets[world_name], subject, cameras)
        cases = answer_envmap_cases(answers, frame, self.model.rig, envmaps, answer_masks(answers, frame))
        if inputs is None:
            single_input = load_fit_views(self.inputs.datasets[world_name], subject, cameras=[frontal])
        else:
            single_input = select_views(inputs, [frontal])
        single_record = {"mesh": "the dataset's tracked mesh", "mask": "the dataset's", "focal": "calibrated"}
        if self.settings.monocular_single_image:
            single_input, single_record = monocular_views(single_input, self.settings.seed)
        single_image = self.fit(world_name, subject, [frontal], "two-stage single image", views=single_input)
        return {
            "source": "world answers relit by image-based relighting (weights recovered from the answers)",
            "input": self.input_description(inputs),
            "seen_in_training": self.seen_in_training(world_name, subject),
            "cameras": cameras,
            "single_image_camera": frontal,
            "single_image_input": single_record,
            "envmaps": envmaps,
            "weight_fit_max_residual": max(c.extra["weight_fit_max_residual"] for c in cases),
            "rows": {
                "multi_view": compare(multi_view_avatar, cases, self.lpips),
                "single_image": compare(single_image, cases, self.lpips),
            },
        }

    def table3(self) -> None:
        """The lighting-code ablation on flat-lit datasets: every arm (:mod:`relightanyone.evaluation.ablation`)
        relit under the rig lights and compared with the subjects' true OLAT images.

        ``table3``: stage-1 training subjects of each arm decoded from their identity codes, no fitting
        (what the OLAT expansion renders), so nothing can absorb a difference between the arms.
        ``table3_fitted``: held-out subjects fitted on their full-on frame, with every arm when
        ``settings.ablation_fits``, else with the main runs only; under their dataset's lighting code when
        ``settings.flat_fits_with_dataset_code``, else as a capture under an unknown rig lighting.
        """

        stage1_names = self._stage1_dataset_names()
        decoded, fitted = {}, {}
        for world_name, path in sorted(self.inputs.datasets.items()):
            dataset = NormalizedDataset(path)
            if world_name == self.olat_world or dataset.manifest.info.kind != "flat":
                continue
            if dataset.name not in stage1_names:
                raise InputError(
                    f"{path}: dataset {dataset.name!r} is not in stage-1 run {self.inputs.stage1} "
                    f"({stage1_names}); the ablation needs its subjects"
                )
            reference = self.arms["with_lighting_code"].subjects
            known = sorted(s.split("/", 1)[1] for s in reference if s.split("/", 1)[0] == dataset.name)
            for subject in known[: self.settings.subjects_per_dataset]:
                cameras, _ = subject_cameras(path, subject, self.settings.max_views)
                frame = min(
                    NormalizedTorchDataset(dataset, subjects=subject, patterns="full").column("frame")
                )
                tracked = dataset.meshes().get(make_mesh_key(subject, frame))
                tracked = (
                    None
                    if tracked is None
                    else torch.as_tensor(np.asarray(tracked), dtype=torch.float32, device=self.device)
                )
                self.inputs_images.setdefault(f"{world_name}/{subject}", self._first_image(path, subject))
                avatars = {
                    row: decoded_avatar(arm.model, arm_subject_index(arm, dataset.name, subject), tracked, {})
                    for row, arm in self.arms.items()
                }
                decoded[f"{world_name}/{subject}"] = self._ablation_entry(
                    world_name, subject, cameras, avatars
                )
            input_dataset = dataset.name if self.settings.flat_fits_with_dataset_code else None
            for subject in self.held_out_subjects(world_name):
                cameras, _ = subject_cameras(path, subject, self.settings.max_views)
                if self.settings.ablation_fits:
                    avatars = {
                        row: self.fit(
                            world_name,
                            subject,
                            cameras,
                            f"two-stage fit, {row}",
                            model=arm.model,
                            data=arm_dataset(arm, dataset.name, path),
                            input_dataset=input_dataset,
                        )
                        for row, arm in self.arms.items()
                    }
                else:
                    avatars = {
                        "two_stage": self.fit(
                            world_name, subject, cameras, "two-stage multi-view", input_dataset=input_dataset
                        )
                    }
                fitted[f"{world_name}/{subject}"] = self._ablation_entry(
                    world_name, subject, cameras, avatars
                )
        self.tables["table3"] = decoded
        self.tables["table3_fitted"] = fitted

    def _ablation_entry(self, world_name: str, subject: str, cameras: list[str], avatars: dict) -> dict:
        """A Table-3 entry: every avatar relit under the rig lights and compared with the subject's truth."""
        cases, source = self.olat_cases(world_name, subject, cameras)
        return {
            "source": source,
            "seen_in_training": self.seen_in_training(world_name, subject),
            "cameras": cameras,
            "lights": [c.label for c in cases],
            "rows": {row: compare(avatar, cases, self.lpips) for row, avatar in avatars.items()},
        }

    def _first_image(self, path: Path, subject: str) -> np.ndarray:
        """(H, W, 3) the subject's first full-on row (the input column of the image grids)."""

        return image_hwc(NormalizedTorchDataset(path, subjects=subject, patterns="full")[0])

    def held_out_subjects(self, world_name: str) -> list[str]:
        """The evaluated subjects of the settings' held-out split in one world dataset."""
        return test_subjects(self.inputs, world_name, self.settings.subjects_per_dataset, self.settings.split)

    def seen_in_training(self, world_name: str, subject: str) -> list[str]:
        """Labels of the runs that trained on this subject (Table 3's decoded training subjects)."""
        key = f"{NormalizedDataset(self.inputs.datasets[world_name]).name}/{subject}"
        return [run.label for run in runs_that_trained(key, self.training_runs)]

    def _stage1_dataset_names(self) -> list[str]:
        info = read_run_info(self.inputs.stage1)
        return [d["name"] for d in info["datasets"]]

    def run(self) -> dict:
        """All tables; returns the JSON-ready results (per-subject and mean metrics)."""
        self.table1_and_2()
        self.table3()
        for name, table in self.tables.items():
            entries = {}
            means: dict[str, dict[str, list[float]]] = {}
            for key, entry in table.items():
                summaries = {row: comparison.summary() for row, comparison in entry["rows"].items()}
                entries[key] = {k: v for k, v in entry.items() if k != "rows"} | {"metrics": summaries}
                for row, summary in summaries.items():
                    for metric, value in summary.items():
                        means.setdefault(row, {}).setdefault(metric, []).append(value)
            self.results[name] = {
                "budgets": {row: self.budgets.get(row) for row in means},
                "subjects": entries,
                "mean": {
                    row: {
                        m: int(np.sum(v)) if m == "images" else float(np.mean(v)) for m, v in metrics.items()
                    }
                    for row, metrics in means.items()
                },
            }
        self.results["ablation"] = {
            "arms": {
                row: {"runs": list(arm.runs), "lighting_code": arm.lighting_code}
                for row, arm in self.arms.items()
            },
            "budgets_agree": budgets_agree(self.arms),
        }
        self.results["light_indices"] = self.light_indices
        self.results["olat_dataset"] = self.olat_world
        return self.results
