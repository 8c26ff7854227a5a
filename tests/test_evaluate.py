"""Evaluation: metrics, answer warping, light and frame matching, and the tables end to end on the sphere world."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers.sphere_world import (
    LIGHTS,
    RIG_INTENSITY,
    SIZE,
    build_sphere_world,
    sphere_camera,
    train_ablation_arms,
    true_olat_image,
)

from relightanyone.evaluation.cases import relight_weights
from relightanyone.evaluation.report import write_report
from relightanyone.evaluation.truth import (
    WorldAnswers,
    match_lights,
    read_answer_image,
    warp_native_to_row,
    world_to_normalized,
)
from relightanyone.model.metrics import masked_psnr, masked_rmse, masked_ssim
from relightanyone.pipelines.report.html import markdown_to_html
from relightanyone.render.camera import crop_intrinsics, resize_intrinsics
from relightanyone.render.envmap import save_envmap


def test_metrics_on_known_errors():
    target = torch.rand(2, 3, 16, 16) * 0.5
    mask = torch.zeros(2, 1, 16, 16)
    mask[:, :, 4:12, 4:12] = 1
    prediction = target + 0.1 * mask
    prediction[:, :, :2] = 0.9  # outside the mask: ignored
    assert torch.allclose(masked_rmse(prediction, target, mask), torch.full((2,), 0.1), atol=1e-5)
    assert torch.allclose(masked_psnr(prediction, target, mask), torch.full((2,), 20.0), atol=1e-3)
    assert torch.allclose(masked_ssim(target, target, mask), torch.ones(2), atol=1e-5)
    assert (masked_ssim(target + 0.2 * torch.randn_like(target) * mask, target, mask) < 0.9).all()


def test_warp_is_undistorted_crop_and_area_resize():
    rng = np.random.default_rng(0)
    native = cv2.GaussianBlur(rng.random((64, 80, 3)).astype(np.float32), (5, 5), 1.0)
    K_native = np.array([[100.0, 0, 39.5], [0, 100.0, 31.5], [0, 0, 1]])
    x0, y0, scale, width, height = 8, 4, 0.5, 24, 20
    K_row = resize_intrinsics(crop_intrinsics(K_native, x0, y0), scale, scale)
    warped = warp_native_to_row(native, K_native, np.zeros(5), K_row, width, height)
    crop = native[y0 : y0 + 2 * height, x0 : x0 + 2 * width]
    expected = crop.reshape(height, 2, width, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(warped, expected, atol=1e-5)
    # With distortion, the warp is OpenCV's undistortion of the native image.
    dist = np.array([-0.2, 0.05, 0.0, 0.0, 0.0])
    undistorted = cv2.undistort(native, K_native, dist, None, K_native)
    same = warp_native_to_row(native, K_native, dist, K_native, 80, 64)
    np.testing.assert_allclose(
        same[10:-10, 10:-10], undistorted[10:-10, 10:-10], atol=6e-3
    )  # OpenCV maps in 1/32 px


def test_world_to_normalized_recovers_the_alignment():
    rng = np.random.default_rng(1)

    def rigid(angle, axis, t):
        R, _ = cv2.Rodrigues(np.asarray(axis, float) * angle)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, t
        return M

    A = rigid(0.1, [0, 1, 0], [0.01, -0.02, 0.03])
    P = rigid(0.05, [1, 0, 0], [0.0, 0.01, 0.0])
    pairs = []
    for _ in range(5):
        world = rigid(rng.uniform(0, 3), rng.normal(size=3) / np.sqrt(3), rng.normal(size=3))
        pairs.append((world, world @ P @ np.linalg.inv(A)))
    np.testing.assert_allclose(world_to_normalized(pairs, P), A, atol=1e-9)


def test_light_matching_and_relight_weights():
    rig = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-1.0, 0, 0]])
    order, worst = match_lights(rig[[2, 0, 3]] + 0.01, rig)
    assert order == [2, 0, 3] and worst == pytest.approx(0.01 * np.sqrt(3))
    with pytest.raises(ValueError, match="do not match"):
        match_lights(rig[[0]] + 0.6, rig)
    rng = np.random.default_rng(2)
    olat = rng.random((4, 200, 3))
    weights = rng.random((4, 3))
    relit = np.einsum("lc,lpc->pc", weights, olat)
    np.testing.assert_allclose(relight_weights(olat, relit), weights, atol=1e-9)


def write_sphere_answers(root: Path, paths: dict) -> Path:
    """A world-shaped answers folder for the sphere world: d1 = olat (test s02), d2 = flat (test f01)."""
    answers = root / "answers"
    subjects = {"d1": {"s00": "train", "s01": "train", "s02": "test"}, "d2": {"f00": "train", "f01": "test"}}
    (answers / "envmaps").mkdir(parents=True)
    (answers / "splits.json").write_text(json.dumps(subjects))
    (answers / "answer_lights.json").write_text(
        json.dumps(
            {
                "rig": "d1",
                "rig_indices": [0, 1, 2, 3],
                "positions": LIGHTS.tolist(),
                "intensities": np.full((4, 3), RIG_INTENSITY).tolist(),
            }
        )
    )
    save_envmap(answers / "envmaps" / "env_000.exr", torch.ones(3, 10, 20))
    weights = np.array([[0.5, 0.4, 0.3], [0.1, 0.1, 0.2], [0.8, 0.9, 1.0], [0.2, 0.2, 0.2]])
    for dataset, split in subjects.items():
        cameras = {}
        for c in range(4):
            K, w2c = sphere_camera(c)
            cameras[f"cam{c:02d}"] = {
                "K": K.tolist(),
                "w2c": w2c.tolist(),
                "dist": [0.0] * 5,
                "width": SIZE,
                "height": SIZE,
            }
        (answers / dataset).mkdir()
        (answers / dataset / "truth.json").write_text(json.dumps({"cameras": cameras, "head_poses": []}))
        # OLAT answers of every subject (a generated world renders training subjects' on demand), env-map
        # answers of the held-out ones.
        for subject, role in split.items():
            for c in range(4):
                olat = [true_olat_image(subject, c, k)[0] for k in range(4)]
                for k, image in enumerate(olat):
                    path = answers / dataset / "olat" / subject / f"cam{c:02d}" / f"{k:03d}.exr"
                    path.parent.mkdir(parents=True, exist_ok=True)
                    save_envmap(path, torch.from_numpy(image).permute(2, 0, 1))
                if role != "test":
                    continue
                relit = np.einsum("lc,lhwc->hwc", weights, np.stack(olat)).astype(np.float32)
                path = answers / dataset / "relit" / subject / f"cam{c:02d}" / "env_000.exr"
                path.parent.mkdir(parents=True, exist_ok=True)
                save_envmap(path, torch.from_numpy(relit).permute(2, 0, 1))
    return root


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    from relightanyone.evaluation.run import run_evaluation
    from relightanyone.evaluation.tables import EvaluationInputs, EvaluationSettings

    root = tmp_path_factory.mktemp("evaluate")
    paths = build_sphere_world(root / "world", flat=True, single_stage=True)
    world = write_sphere_answers(root / "synthetic", paths)
    inputs = EvaluationInputs(
        datasets={"d1": paths["data"], "d2": paths["flat"]},
        stage1=paths["stage1"],
        stage2=paths["stage2"],
        single_stage=paths["single_stage"],
        answers=WorldAnswers(world),
        ablation=train_ablation_arms(paths),
    )
    settings = EvaluationSettings(inversion_iterations=3, finetune_iterations=2, max_views=3, progress=False)
    out = root / "out"
    results = run_evaluation(inputs, settings, out, json_copy=root / "bench" / "evaluation.json")
    return {"results": results, "out": out, "root": root, "paths": paths, "world": world}


def test_answers_are_warped_onto_the_analytic_truth(evaluated):
    from relightanyone.evaluation.cases import answer_frame, answer_masks, answer_olat_cases
    from relightanyone.model.fit.fitter import load_relightable_model

    answers = WorldAnswers(evaluated["world"])
    paths = evaluated["paths"]
    rig = load_relightable_model(paths["stage1"], paths["stage2"]).rig
    frame = answer_frame(answers, "d2", paths["flat"], "f01", ["cam01", "cam02"])
    np.testing.assert_allclose(frame.world_to_norm, np.eye(4), atol=1e-9)
    cases = answer_olat_cases(answers, frame, rig, [1, 3], answer_masks(answers, frame))
    assert [c.label for c in cases] == ["light 01", "light 03"]
    for case, light in zip(cases, [1, 3], strict=True):
        torch.testing.assert_close(case.light.positions[0], torch.tensor(LIGHTS[light], dtype=torch.float32))
        for view in case.views:
            truth, mask = true_olat_image("f01", int(view.camera[3:]), light)
            inside = view.mask > 0.5
            assert inside.sum() > 0.5 * mask.sum()  # eroded silhouette
            assert not inside[~mask].any()
            np.testing.assert_allclose(view.image[inside], truth[inside], atol=2e-3, rtol=2e-3)
    assert read_answer_image(answers.olat_path("d2", "f01", "cam00", 0)).shape == (SIZE, SIZE, 3)


def test_answer_masks_stay_inside_the_row_masks(evaluated):
    """The tables compare only what the dataset calls the subject: a row mask cut at some line limits
    the answer mask to it."""
    from relightanyone.evaluation.cases import answer_frame, answer_masks

    answers = WorldAnswers(evaluated["world"])
    frame = answer_frame(answers, "d2", evaluated["paths"]["flat"], "f01", ["cam01", "cam02"])
    assert set(frame.row_masks) == {"cam01", "cam02"}
    full = answer_masks(answers, frame)
    cut = {camera: mask.copy() for camera, mask in frame.row_masks.items()}
    for mask in cut.values():
        mask[mask.shape[0] // 2 :] = 0  # a neck line through the middle
    frame.row_masks = cut
    limited = answer_masks(answers, frame)
    for camera, mask in cut.items():
        half = mask.shape[0] // 2
        assert full[camera][:half].sum() > 0 and full[camera][half:].sum() > 0  # the cut removes something
        np.testing.assert_array_equal(limited[camera], full[camera] * (mask > 0.5))
        assert limited[camera][half:].sum() == 0


def test_tables_and_report(evaluated):
    results, out = evaluated["results"], evaluated["out"]
    table1 = results["table1"]["subjects"]["d1/s02"]
    assert table1["source"].startswith("world answers")
    assert table1["lights"] == ["light 00", "light 01", "light 02", "light 03"]
    for row in ("two_stage", "single_stage"):
        metrics = table1["metrics"][row]
        assert metrics["images"] == 4 * 3
        assert np.isfinite([metrics["psnr"], metrics["rmse"], metrics["ssim"]]).all()
        assert 0 < metrics["rmse"] < 1 and -1 <= metrics["ssim"] <= 1
    table2 = results["table2"]["subjects"]["d1/s02"]
    assert table2["weight_fit_max_residual"] < 1e-2
    assert set(table2["metrics"]) == {"multi_view", "single_image"}
    # The ablation's three trained arms on the stage-1 training subject (decoded) and on the held-out
    # one (fitted), each with its training budget.
    arms = {"with_lighting_code", "without_lighting_code", "colour_matrix"}
    for table, subject in (("table3", "d2/f00"), ("table3_fitted", "d2/f01")):
        entry = results[table]["subjects"][subject]
        assert set(entry["metrics"]) == arms
        assert entry["metrics"]["with_lighting_code"]["images"] == 4 * 3
        # Differently trained arms give different relit images, so the ablation measures something.
        rmse = {entry["metrics"][arm]["rmse"] for arm in arms}
        assert len(rmse) == 3, entry["metrics"]
        assert set(results[table]["budgets"]) == arms
    assert results["ablation"]["budgets_agree"] is True
    budget = results["table3"]["budgets"]["without_lighting_code"]
    assert (
        budget["stage1"]["iterations"] == 6
        and budget["samples"] == budget["stage1"]["samples"] + (budget["stage2"]["samples"])
    )
    assert results["table1"]["budgets"]["single_stage"]["single_stage"]["stage"] == "single-stage"
    # A training subject is named by every run that trained on it: stage 1, the ablation arms' stage 1
    # runs and the colour warm-ups of their datasets.
    seen = results["table3"]["subjects"]["d2/f00"]["seen_in_training"]
    assert seen[0] == "stage 1", seen
    assert all(label.endswith("stage 1") or label == "colour warm-up" for label in seen), seen
    saved = json.loads((out / "evaluation.json").read_text())
    assert saved["table1"]["mean"]["two_stage"]["psnr"] == pytest.approx(
        table1["metrics"]["two_stage"]["psnr"]
    )
    assert (evaluated["root"] / "bench" / "evaluation.json").read_text() == (
        out / "evaluation.json"
    ).read_text()
    assert len(saved["goals"]) == 8
    assert "training budget" in report_text(out) and "3×3 colour matrix" in report_text(out)
    # One held-out subject per dataset: a smoke run, whose comparisons have no interval and no win.
    assert saved["run_kind"] == "smoke run" and saved["held_out_subjects"] == {"d1": 1, "d2": 1}
    assert saved["protocol"]["split"] == "test" and len(saved["protocol_sha256"]) == 64
    comparison = saved["table1"]["comparisons"]["two_stage vs single_stage"]["psnr"]
    assert comparison["subjects"] == 1 and comparison["low"] is None and comparison["win"] is False
    assert {"psnr_srgb", "ssim_srgb", "rmse_srgb"} <= set(saved["table1"]["mean"]["two_stage"])
    report = (out / "report.md").read_text()
    assert "synthetic world" in report and "different data, not comparable" in report
    assert (
        "| 30.06 | 0.87 | 0.0655 |" in report
        and "smoke run" in report.lower()
        and saved["lpips"].startswith("skipped")
    )
    for grid in [g for names in saved["grids"].values() for g in names]:
        image = cv2.imread(str(out / grid))
        assert image is not None and image.shape[0] >= 128
    assert {Path(g).name for names in saved["grids"].values() for g in names} == {
        "table1_d1_s02.png",
        "table2_d1_s02.png",
        "table3_d2_f00.png",
        "table3_fitted_d2_f01.png",
    }


def report_text(out: Path) -> str:
    return (out / "report.md").read_text()


def test_batched_point_light_renders_match_relight(evaluated):
    from relightanyone.evaluation.cases import LightCase, view_cameras
    from relightanyone.evaluation.single_stage import SingleStageFitter, load_single_stage_run
    from relightanyone.evaluation.tables import EvalView, render_point_lights, render_weighted_rig
    from relightanyone.model.fit.fitter import FitSettings, Fitter, load_relightable_model
    from relightanyone.model.fit.views import load_fit_views
    from relightanyone.render.lights import PointLights

    paths = evaluated["paths"]
    views = load_fit_views(paths["data"], "s02", cameras=["cam00", "cam03"])
    settings = FitSettings(inversion_iterations=1, finetune_iterations=1, progress=False)
    model = load_relightable_model(paths["stage1"], paths["stage2"])
    avatars = [
        Fitter(model, views, settings).avatar(),
        SingleStageFitter(load_single_stage_run(paths["single_stage"]), views, settings).avatar(),
    ]
    cameras = view_cameras(
        [EvalView(c, *sphere_camera(int(c[3:])), SIZE, SIZE, None, None) for c in ("cam00", "cam03")]
    )
    lights = PointLights(
        torch.tensor(LIGHTS[[2, 0]], dtype=torch.float32), torch.tensor([[1.0, 2, 3], [2.5] * 3])
    )
    # Environment cases: the weighted rig is shaded in one pass, as the avatar relights any light set.
    weights = np.array([[0.5, 1.0, 2.0], [0.0, 0.0, 0.0]])
    cases = [
        LightCase("env", [], weights=weights, basis=lights),
        LightCase("both", [], weights=np.ones((2, 3)), basis=lights),
    ]
    for avatar in avatars:
        stacked = render_point_lights(avatar, cameras, lights)
        assert stacked.shape == (2, 2, 3, SIZE, SIZE) and stacked.abs().sum() > 0
        for k in range(2):
            single = avatar.relight(
                cameras, PointLights(lights.positions[k : k + 1], lights.intensities[k : k + 1])
            )
            torch.testing.assert_close(stacked[k], single, atol=1e-5, rtol=1e-4)
        env, both = render_weighted_rig(avatar, cameras, cases)
        scaled = PointLights(lights.positions[:1], lights.intensities[:1] * torch.tensor([[0.5, 1.0, 2.0]]))
        torch.testing.assert_close(env, avatar.relight(cameras, scaled), atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(both, avatar.relight(cameras, lights), atol=1e-5, rtol=1e-4)


def test_full_on_equals_sum_of_olat_in_a_consistent_dataset(evaluated):
    from relightanyone.evaluation.cases import olat_sum_over_full_on

    ratio = olat_sum_over_full_on(evaluated["paths"]["data"], "s00", ["cam00", "cam02"])
    assert ratio == pytest.approx(1.0, abs=1e-3)
    assert olat_sum_over_full_on(evaluated["paths"]["data"], "s02", ["cam00"]) is None  # no OLAT rows


def test_warp_matches_the_ingest_filter_at_a_fractional_scale():
    """A row 1.5× coarser than the native image: the warp is ingest's undistorted crop + area resize."""
    from relightanyone.ingest.steps import undistort_crop_resize

    rng = np.random.default_rng(2)
    native = cv2.GaussianBlur(rng.random((120, 150, 3)).astype(np.float32), (5, 5), 1.0)
    K_native = np.array([[140.0, 0, 74.5], [0, 140.0, 59.5], [0, 0, 1]])
    dist = np.array([-0.1, 0.02, 0.001, -0.001, 0.0])
    box = (20, 10, 116, 106)  # 96 px to 64 px
    ingested, K_row = undistort_crop_resize(native, K_native, dist, box, 64)
    warped = warp_native_to_row(native, K_native, dist, K_row, 64, 64)
    np.testing.assert_allclose(warped, ingested, atol=1e-5)


def test_report_md_escapes_names_from_the_data(tmp_path):
    key = "d1/<img src=x onerror=alert(1)>|[a](javascript:alert(1))"
    metrics = {"two_stage": {"psnr": 30.0, "images": 4}, "single_stage": {"psnr": 28.0, "images": 4}}
    results = {
        "inputs": {
            "world": "w`orld",
            "datasets": {"d1": "<script>x</script>"},
            "stage1": "s1",
            "stage2": "s2",
        },
        "table1": {
            "mean": metrics,
            "subjects": {
                key: {
                    "source": "**bold**",
                    "cameras": ["c|1", "c<2>"],
                    "metrics": metrics,
                    "seen_in_training": ["<r>"],
                }
            },
        },
    }
    report = write_report(tmp_path, results, {}, {})
    html = markdown_to_html(report.read_text())
    assert not re.search(r"<(img|script|a|r)\b", html), html
    assert "&lt;img src=x onerror=alert(1)&gt;|[a](javascript:alert(1))" in html
    assert "<code>w`orld</code>" in html and "<code>&lt;script&gt;x&lt;/script&gt;</code>" in html
    assert "**bold**" in html and "c|1, c&lt;2&gt;" in html
    # Every table row still has one cell per column.
    for row in re.findall(r"<tr>(.*?)</tr>", html, flags=re.S):
        assert row.count("<td>") in (0, 3), row


def test_held_out_inputs_are_lit_by_an_unknown_lighting(evaluated):
    """Table 1/2 fit the held-out subject on the world's render under its own lighting, which is the
    analytic sphere under the weighted rig (the renderer is linear in its lights)."""
    from relightanyone.evaluation.cases import answer_frame
    from relightanyone.evaluation.unknown_lighting import relit_input_image, subject_input_lighting

    entry = evaluated["results"]["table1"]["subjects"]["d1/s02"]
    assert entry["input"]["images"].startswith("the world's render")
    assert "training captures" in entry["input"]["prior"]
    answers = WorldAnswers(evaluated["world"])
    lighting = subject_input_lighting(answers, "d1", "s02")
    assert entry["input"]["lighting"]["level"] == pytest.approx(lighting.level, abs=1e-4)
    frame = answer_frame(answers, "d1", evaluated["paths"]["data"], "s02", ["cam01"])
    image = relit_input_image(answers, frame, "cam01", lighting.weights)
    truth = sum(lighting.weights[k] * true_olat_image("s02", 1, k)[0] for k in range(4))
    inside = true_olat_image("s02", 1, 0)[1]
    np.testing.assert_allclose(image[inside], truth[inside], rtol=5e-3, atol=5e-3)
    table2 = evaluated["results"]["table2"]["subjects"]["d1/s02"]
    assert table2["input"] == entry["input"]
    # The single-image fit gets what one image yields (see test_single_image.py).
    single = table2["single_image_input"]
    assert single["mask"].startswith("foreground") and "generic_fov_deg" in single["focal"]


def test_the_baseline_variant_is_chosen_on_validation_subjects_only(evaluated, tmp_path):
    """Several single-stage runs: the one with the best validation relighting is Table 1's baseline; with no
    validation subjects the choice is refused instead of being made on test subjects."""
    import shutil

    from helpers.sphere_world import tiny_stage1_preset, tiny_stage2_preset

    from relightanyone.errors import InputError
    from relightanyone.evaluation.tables import Evaluation, EvaluationInputs, EvaluationSettings
    from relightanyone.model.train.stage2 import Stage2Config, train_stage2

    paths = evaluated["paths"]
    masked = tmp_path / "single-masked"
    train_stage2(
        Stage2Config(
            paths["data"],
            masked,
            tiny_stage2_preset(),
            single_stage=True,
            single_stage_loss="masked",
            stage1_preset=tiny_stage1_preset(iterations=4, crop_size=SIZE, held_out_cameras=0),
            progress=False,
        )
    )
    settings = EvaluationSettings(inversion_iterations=1, finetune_iterations=1, max_views=2, progress=False)

    def inputs(world: Path) -> EvaluationInputs:
        return EvaluationInputs(
            datasets={"d1": paths["data"], "d2": paths["flat"]},
            stage1=paths["stage1"],
            stage2=paths["stage2"],
            single_stage=paths["single_stage"],
            single_stage_variants=(masked,),
            answers=WorldAnswers(world),
        )

    with pytest.raises(InputError, match="no validation subjects"):
        Evaluation(inputs(evaluated["world"]), settings)
    world = tmp_path / "world"
    shutil.copytree(evaluated["world"], world)
    splits = json.loads((world / "answers" / "splits.json").read_text())
    splits["d1"]["s01"] = "val"  # a training-split subject with OLAT rows, never a test subject
    (world / "answers" / "splits.json").write_text(json.dumps(splits))
    evaluation = Evaluation(inputs(world), settings)
    choice = evaluation.results["baseline_choice"]
    assert choice["subjects"] == ["s01"] and len(choice["candidates"]) == 2
    scores = {run: entry["validation_psnr"] for run, entry in choice["candidates"].items()}
    assert choice["chosen"] == max(scores, key=scores.get)
    assert str(evaluation.inputs.single_stage) == choice["chosen"]
    assert "masked loss" in choice["candidates"][str(masked)]["label"]


def test_evaluate_command_takes_the_ablation_arms(evaluated, tmp_path):
    """The command line of the demo's evaluate stage: arms by name, the main runs' fits only in Table 3b;
    an arm whose stage 1 contradicts its name is refused in one line."""
    from click.testing import CliRunner

    from relightanyone.cli import cli

    paths, root = evaluated["paths"], evaluated["paths"]["root"]
    arm = {
        name: [str(root / f"{name}-stage1"), str(root / f"{name}-stage2")]
        for name in ("no-zl", "colour-matrix")
    }
    base = [
        "evaluate",
        "--world",
        str(evaluated["world"]),
        "--data",
        f"d1={paths['data']}",
        "--data",
        f"d2={paths['flat']}",
        "--stage1",
        str(paths["stage1"]),
        "--stage2",
        str(paths["stage2"]),
        "--fit-iterations",
        "1",
        "1",
        "--max-views",
        "2",
        "--lights-subset",
        "2",
        "--quiet",
    ]
    wrong = CliRunner().invoke(
        cli, [*base, "--ablation", "with-zl", *arm["no-zl"], "--out", str(tmp_path / "w")]
    )
    assert wrong.exit_code == 1 and "trained without" in wrong.output and "Traceback" not in wrong.output
    args = [*base, "--ablation", "no-zl", *arm["no-zl"], "--ablation", "colour-matrix", *arm["colour-matrix"]]
    result = CliRunner().invoke(cli, [*args, "--no-ablation-fits", "--out", str(tmp_path / "e")])
    assert result.exit_code == 0, result.output
    saved = json.loads((tmp_path / "e" / "evaluation.json").read_text())
    assert set(saved["table3"]["mean"]) == {"with_lighting_code", "without_lighting_code", "colour_matrix"}
    assert set(saved["table3_fitted"]["mean"]) == {"two_stage"}
    assert saved["settings"]["unknown_lighting"] and saved["settings"]["monocular_single_image"]
