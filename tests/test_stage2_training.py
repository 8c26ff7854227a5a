"""Stage-2 and single-stage training end to end on a tiny OLAT sphere world.

The world: Lambertian spheres (the stage-1 test template) lit by a four-light rig, seen by three cameras,
with one OLAT frame per light and one full-on frame per subject, plus ``lights.arrow``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from helpers.sphere_world import LIGHTS, SIZE, lambert_sphere, rig_lights, sphere_camera, sphere_row
from helpers.sphere_world import tiny_stage2_preset as sphere_tiny_stage2_preset
from helpers.stage1_world import sphere_dataset, sphere_mesh, tiny_stage1_preset, write_dataset
from helpers.torchrun import run_torchrun

from relightanyone.cli import cli
from relightanyone.model.networks.reflectance import camera_centres
from relightanyone.model.networks.stage2 import texel_mesh_normals
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.stage1 import Stage1Config, train_stage1
from relightanyone.model.train.stage2 import Stage2Config, Stage2Trainer, train_stage2
from relightanyone.render.camera import look_at_w2c

LIGHT_INTENSITY = 2.5  # radiant intensity: about 2.5 W/m² on the sphere, radiance 0.2-0.5 per light


def stage2_camera(c: int) -> tuple[np.ndarray, np.ndarray]:
    """(K, w2c) of camera ``c``: the sphere world's intrinsics, the views 0.6 rad apart."""
    K, _ = sphere_camera(c)
    angle = 0.6 * (c - 1)
    return K, look_at_w2c(0.5 * np.array([np.sin(angle), 0.1, np.cos(angle)]), np.zeros(3), [0.0, 1.0, 0.0])


def write_olat_dataset(root: Path, name: str = "olat", subjects: int = 2, cameras: int = 3) -> Path:
    rig = np.full((len(LIGHTS), 3), LIGHT_INTENSITY)
    rng = np.random.default_rng(3)
    lighting = "4-light OLAT rig + full-on"
    with sphere_dataset(root, name, "olat", lighting, "stage2 test sphere world", {"name": name}) as writer:
        writer.write_lights(rig_lights(LIGHT_INTENSITY))
        for s in range(subjects):
            subject = f"s{s:02d}"
            albedo = rng.uniform(0.3, 0.9, 3)
            with writer.part(subject) as part:
                part.add_mesh(sphere_mesh(subject))
                for c in range(cameras):
                    K, w2c = stage2_camera(c)
                    patterns = {"full": slice(None)} | {f"olat-{k:03d}": slice(k, k + 1) for k in range(4)}
                    for pattern, lights in patterns.items():
                        image, mask = lambert_sphere(1.0, albedo, K, w2c, LIGHTS[lights], rig[lights])
                        part.add(sphere_row(name, subject, c, pattern, "train", image, mask, (K, w2c)))
    return root / name


def tiny_stage2_preset(**changes):
    """The sphere world's stage-2 preset, trained a little longer and on full-on frames half the time."""
    longer = dict(
        iterations=10,
        normal_anneal_iterations=5,
        albedo_anneal_iterations=5,
        checkpoint_every=5,
        full_on_fraction=0.5,
    )
    return sphere_tiny_stage2_preset(**(longer | changes))


@pytest.fixture(scope="module")
def olat_world(tmp_path_factory) -> tuple[Path, Path]:
    """(OLAT dataset folder, stage-1 run trained on its full-on frames)."""
    root = tmp_path_factory.mktemp("olat-world")
    dataset = write_olat_dataset(root)
    run = root / "stage1"
    train_stage1(
        Stage1Config(
            [dataset],
            run,
            tiny_stage1_preset(iterations=4, crop_size=SIZE, held_out_cameras=0),
            progress=False,
            evaluate=False,
        )
    )
    return dataset, run


def _fixed_batch_losses(trainer: Stage2Trainer, batches: list[dict]) -> float:
    """Mean image objective 10 L1 + 0.2 (1 - SSIM) over fixed batches (the regularisers start at zero)."""
    with torch.no_grad():
        terms = [trainer.loss(batch, 0)[1] for batch in batches]
    return float(np.mean([10.0 * t["l1"] + 0.2 * t["ssim"] for t in terms]))


def test_stage2_trains_with_stage1_frozen_and_lowers_the_loss(olat_world, tmp_path):
    dataset, run = olat_world
    trainer = Stage2Trainer(
        Stage2Config(dataset, tmp_path / "s2", tiny_stage2_preset(), stage1_run=run, progress=False)
    )
    assert trainer.frames.subjects == ["olat/s00", "olat/s01"]
    assert len(trainer.frames.olat) == 2 * 3 * 4 and len(trainer.frames.full_on) == 2 * 3
    assert trainer.albedo_per_colour.shape == (3,) and (trainer.albedo_per_colour > 0).all()
    stage1_before = {k: v.clone() for k, v in trainer.stage1.state_dict().items()}
    batches = [trainer.batch(i) for i in range(3)]
    # An OLAT batch lights one rig light per sample; a full-on sample has all four.
    counts = {int((b["light_intensities"].abs().sum(-1) > 0).sum(-1).max()) for b in batches}
    assert counts <= {1, 4}
    before = _fixed_batch_losses(trainer, batches)
    metrics = trainer.train()
    after = _fixed_batch_losses(trainer, batches)
    assert after < 0.9 * before, (before, after)
    assert all(torch.equal(v, trainer.stage1.state_dict()[k]) for k, v in stage1_before.items())
    assert all(not p.requires_grad for p in trainer.stage1.parameters()) and not trainer.stage1.training
    out = tmp_path / "s2"
    assert metrics["mode"] == "stage2" and metrics["seconds_per_iteration"] > 0
    assert {"albedo", "negative_diffuse", "monochrome", "normal"} <= set(metrics["last_losses"])
    checkpoint = load_checkpoint(out / "checkpoint.pt")
    assert checkpoint["iteration"] == 10 and checkpoint["single_stage"] is False
    info = json.loads((out / "run.json").read_text())
    assert info["stage"] == "stage2" and info["frames"] == {"full_on": 6, "olat": 24} and info["lights"] == 4
    # The albedo follows the colours stage 2 is given (a shared prior let it predict one albedo for all).
    subjects = batches[0]["subject_index"]
    with torch.no_grad():
        vertices, gaussians = trainer.stage1(subjects, torch.full_like(subjects, trainer.lighting_index))
        inputs = (
            gaussians.means,
            texel_mesh_normals(vertices, trainer.stage1.binding),
            camera_centres(batches[0]["w2c"]),
        )
        albedo = trainer.trainable(gaussians.colours, *inputs).albedo
        brighter = trainer.trainable(gaussians.colours * 2.0, *inputs).albedo
    assert float(brighter.mean() / albedo.mean()) > 1.5


def test_resumed_stage2_run_ends_with_the_uninterrupted_weights(olat_world, tmp_path):
    dataset, run = olat_world
    preset = tiny_stage2_preset(iterations=4, checkpoint_every=2)
    whole = Stage2Trainer(Stage2Config(dataset, tmp_path / "whole", preset, stage1_run=run, progress=False))
    whole.train()
    Stage2Trainer(
        Stage2Config(
            dataset, tmp_path / "split", preset.replace(iterations=2), stage1_run=run, progress=False
        )
    ).train()
    resumed = Stage2Trainer(Stage2Config(dataset, tmp_path / "split", preset, stage1_run=run, progress=False))
    resumed.train()
    assert resumed.start == 2
    for name, tensor in whole.trainable.state_dict().items():
        assert torch.equal(tensor, resumed.trainable.state_dict()[name]), name


def test_single_stage_flag_trains_through_the_same_trainer(olat_world, tmp_path):
    dataset, _ = olat_world
    config = Stage2Config(
        dataset,
        tmp_path / "single",
        tiny_stage2_preset(),
        single_stage=True,
        progress=False,
        stage1_preset=tiny_stage1_preset(crop_size=SIZE),
    )
    trainer = Stage2Trainer(config)
    assert trainer.albedo_per_colour is None and not hasattr(trainer, "stage1")
    batches = [trainer.batch(i) for i in range(3)]
    before = _fixed_batch_losses(trainer, batches)
    metrics = trainer.train()
    after = _fixed_batch_losses(trainer, batches)
    assert after < 0.9 * before, (before, after)
    assert metrics["mode"] == "single-stage" and {"geometry", "scale", "offset"} <= set(
        metrics["last_losses"]
    )
    assert load_checkpoint(tmp_path / "single" / "checkpoint.pt")["single_stage"] is True
    # Resuming the finished run in the other mode is refused instead of mixing weights.
    with pytest.raises(ValueError, match="another mode"):
        Stage2Trainer(
            Stage2Config(
                dataset, tmp_path / "single", tiny_stage2_preset(), stage1_run=olat_world[1], progress=False
            )
        ).resume_if_possible()


@pytest.mark.parametrize("single_stage", [False, True], ids=["stage2", "single-stage"])
def test_torchrun_two_gloo_processes_match_one_process_with_the_global_batch(
    olat_world, tmp_path, single_stage
):
    dataset, run = olat_world

    def config(out: Path, batch_size: int) -> Stage2Config:
        return Stage2Config(
            dataset,
            out,
            tiny_stage2_preset(iterations=3, checkpoint_every=3, batch_size=batch_size),
            stage1_run=None if single_stage else run,
            single_stage=single_stage,
            stage1_preset=tiny_stage1_preset(crop_size=SIZE) if single_stage else None,
            progress=False,
            device="cpu",
        )

    run_torchrun("relightanyone.model.train.stage2", "train_stage2", config(tmp_path / "ddp", 1), tmp_path)
    metrics = json.loads((tmp_path / "ddp" / "metrics.json").read_text())
    assert metrics["processes"] == 2 and metrics["processes_in_sync"]
    # Two processes with batch 1 see exactly the samples (views, crops, backgrounds) of one with batch 2.
    train_stage2(config(tmp_path / "single", 2))
    parallel = load_checkpoint(tmp_path / "ddp" / "checkpoint.pt")["model"]
    serial = load_checkpoint(tmp_path / "single" / "checkpoint.pt")["model"]
    # Adam's first steps move each weight by about ±lr whatever the gradient's size, so the few weights
    # whose gradient is ~0 may take either sign from rounding; all others must agree.
    agreeing = sum(int(torch.isclose(parallel[n], t, atol=1e-5, rtol=1e-4).sum()) for n, t in serial.items())
    total = sum(t.numel() for t in serial.values())
    assert agreeing >= 0.999 * total, f"{total - agreeing} of {total} weights differ"
    train_stage2(config(tmp_path / "half", 1))  # one process with half the batch trains otherwise
    half = load_checkpoint(tmp_path / "half" / "checkpoint.pt")["model"]
    assert any(not torch.allclose(half[n], t, atol=1e-5, rtol=1e-4) for n, t in serial.items())


def test_cli_trains_stage2_and_explains_bad_input(olat_world, tmp_path):
    dataset, run = olat_world
    runner = CliRunner()
    result = runner.invoke(
        cli,
        [
            "train",
            "stage2",
            "--data",
            str(dataset),
            "--stage1",
            str(run),
            "--out",
            str(tmp_path / "cli"),
            "--iterations",
            "2",
            "--batch-size",
            "1",
        ],
    )
    assert result.exit_code == 0, result.output
    assert load_checkpoint(tmp_path / "cli" / "checkpoint.pt")["iteration"] == 2
    missing = runner.invoke(cli, ["train", "stage2", "--data", str(dataset), "--out", str(tmp_path / "x")])
    assert missing.exit_code != 0 and "--stage1" in missing.output
    flat = write_dataset(tmp_path, "flat", subjects=1, cameras=2, size=16)
    no_rig = runner.invoke(
        cli, ["train", "stage2", "--data", str(flat), "--single-stage", "--out", str(tmp_path / "y")]
    )
    assert no_rig.exit_code != 0 and "lights.arrow" in no_rig.output
    other = write_olat_dataset(tmp_path, "other", subjects=1, cameras=1)
    unknown = runner.invoke(
        cli,
        ["train", "stage2", "--data", str(other), "--stage1", str(run), "--out", str(tmp_path / "z")],
    )
    assert unknown.exit_code != 0 and "not trained on dataset 'other'" in unknown.output


def test_single_stage_matches_a_two_stage_budget_with_either_loss(olat_world, tmp_path):
    """--match-budget gives the baseline as many training views as stage 1 + stage 2 together; the loss
    variant is recorded, changes the objective, and a run cannot resume with the other one."""
    from relightanyone.model.train.budget import run_budget

    dataset, run = olat_world
    runner = CliRunner()
    stage2 = tmp_path / "stage2"
    base = ["train", "stage2", "--data", str(dataset)]
    made = runner.invoke(cli, [*base, "--stage1", str(run), "--out", str(stage2), "--iterations", "3"])
    assert made.exit_code == 0, made.output
    out = tmp_path / "single"
    single = [
        *base,
        "--single-stage",
        "--single-stage-loss",
        "masked",
        "--batch-size",
        "3",
        "--out",
        str(out),
    ]
    both = runner.invoke(cli, [*single, "--match-budget", str(run), str(stage2), "--iterations", "2"])
    assert both.exit_code != 0 and "not both" in both.output
    result = runner.invoke(cli, [*single, "--match-budget", str(run), str(stage2)])
    assert result.exit_code == 0, result.output
    views = run_budget(run)["samples"] + run_budget(stage2)["samples"]
    budget = run_budget(out)
    assert budget["iterations"] == -(-views // 3) and budget["samples"] >= views > budget["samples"] - 3
    info = json.loads((out / "run.json").read_text())
    assert info["single_stage_loss"] == "masked"
    # A share of that budget (a smoke run), and a share without a budget to take it of.
    half = tmp_path / "half"
    shared = [*single[:-1], str(half), "--match-budget", str(run), str(stage2), "--match-share", "0.5"]
    result = runner.invoke(cli, shared)
    assert result.exit_code == 0, result.output
    assert run_budget(half)["iterations"] == math.ceil(math.ceil(views / 2) / 3)
    alone = runner.invoke(cli, [*single[:-1], str(tmp_path / "alone"), "--match-share", "0.5"])
    assert alone.exit_code != 0 and "--match-share needs --match-budget" in alone.output
    losses = {}
    for variant in ("background", "masked"):
        config = Stage2Config(
            dataset,
            tmp_path / variant,
            tiny_stage2_preset(),
            single_stage=True,
            single_stage_loss=variant,
            progress=False,
            stage1_preset=tiny_stage1_preset(crop_size=SIZE),
        )
        torch.manual_seed(0)
        trainer = Stage2Trainer(config)
        losses[variant] = trainer.loss(trainer.batch(0), 0)[1]["l1"]
    assert losses["background"] != losses["masked"]
    resumed = runner.invoke(cli, [*base, "--single-stage", "--out", str(out), "--iterations", "1"])
    assert resumed.exit_code != 0 and "another mode" in resumed.output


@pytest.mark.parametrize("single_stage", [False, True], ids=["stage2", "single-stage"])
def test_accumulated_micro_batches_give_the_batch_gradient(olat_world, tmp_path, single_stage):
    dataset, run = olat_world
    config = Stage2Config(
        dataset,
        tmp_path / "s2",
        tiny_stage2_preset(batch_size=4),
        stage1_run=None if single_stage else run,
        single_stage=single_stage,
        stage1_preset=tiny_stage1_preset(crop_size=SIZE) if single_stage else None,
        progress=False,
    )
    trainer = Stage2Trainer(config)
    batch = trainer.batch(1)
    gradients = {}
    for parts in (1, 3):
        trainer.config.accumulation = parts
        trainer.optimizer.zero_grad(set_to_none=True)
        terms = trainer.accumulate(batch, 1)
        gradients[parts] = [p.grad.clone() for p in trainer.trainable.parameters() if p.grad is not None]
        assert set(terms) >= {"total", "l1", "ssim"}
    assert len(gradients[1]) == len(gradients[3]) > 0
    for whole, accumulated in zip(gradients[1], gradients[3], strict=True):
        torch.testing.assert_close(accumulated, whole, rtol=1e-4, atol=1e-6)
