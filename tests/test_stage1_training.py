"""Stage-1 training end to end on a tiny sphere world: run folder, held-out metrics, exact resume after
SIGKILL, data-parallel training with two gloo processes, colour warm-up, and the render command."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from helpers.kill_handshake import HANG_GUARD_SECONDS, kill_at, start_python
from helpers.stage1_world import tiny_stage1_preset, train_script, write_dataset

from relightanyone.cli import cli
from relightanyone.model.train.checkpoint import load_checkpoint
from relightanyone.model.train.data import Stage1Data
from relightanyone.model.train.held_out import evaluate_held_out
from relightanyone.model.train.run import load_run
from relightanyone.model.train.stage1 import Stage1Config, build_model, train_stage1

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CAST = np.array([[1.3, 0.1, 0.0], [0.0, 0.9, 0.0], [0.0, 0.05, 0.6]])


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("sphere-world")
    return [write_dataset(root, "da", seed=0), write_dataset(root, "db", cast=CAST, seed=1)]


@pytest.fixture(scope="module")
def trained_run(world, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("run") / "stage1"
    preset = tiny_stage1_preset(iterations=20, checkpoint_every=10, image_every=10)
    metrics = train_stage1(Stage1Config(world, out, preset, progress=False))
    return out, metrics


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["OMP_NUM_THREADS"] = "1"  # two processes on two cores
    return env


def test_training_writes_a_run_and_beats_the_untrained_model(world, trained_run):
    out, metrics = trained_run
    for name in ("checkpoint.pt", "run.json", "metrics.json", "template.obj"):
        assert (out / name).is_file(), name
    assert any((out / "tensorboard").iterdir())
    info = json.loads((out / "run.json").read_text())
    assert info["subjects"] == ["da/s00", "da/s01", "db/s00", "db/s01"]
    assert load_checkpoint(out / "checkpoint.pt")["iteration"] == 20
    assert set(metrics["held_out"]) == {"da", "db"} and metrics["seconds_per_iteration"] > 0
    data = Stage1Data(world, held_out_per_subject=1)
    torch.manual_seed(0)
    untrained = evaluate_held_out(build_model(tiny_stage1_preset(), data, (), data.template_path), data)
    for name in ("da", "db"):
        assert metrics["held_out"][name]["psnr"] > untrained[name]["psnr"] + 1.0, (metrics, untrained)


def test_resume_refuses_a_different_architecture(world, trained_run):
    out, _ = trained_run
    with pytest.raises(ValueError, match="other settings"):
        train_stage1(Stage1Config(world, out, tiny_stage1_preset(z_id_dim=12, iterations=21), progress=False))


def test_sigkill_then_resume_gives_the_uninterrupted_weights(world, tmp_path):
    settings = dict(iterations=10, checkpoint_every=2)
    reference, interrupted = tmp_path / "reference", tmp_path / "interrupted"
    subprocess.run(
        [sys.executable, "-c", train_script(world, reference, **settings)],
        check=True,
        env=_env(),
        timeout=HANG_GUARD_SECONDS,
    )
    script = train_script(world, interrupted, kill_after_checkpoint=4, **settings)
    kill_at(start_python(script, env=_env()), "CHECKPOINT 4")
    checkpoint = interrupted / "checkpoint.pt"
    assert load_checkpoint(checkpoint)["iteration"] == 4
    subprocess.run(
        [sys.executable, "-c", train_script(world, interrupted, **settings)],
        check=True,
        env=_env(),
        timeout=HANG_GUARD_SECONDS,
    )
    expected = load_checkpoint(reference / "checkpoint.pt")
    resumed = load_checkpoint(checkpoint)
    assert resumed["iteration"] == expected["iteration"] == 10
    for name, tensor in expected["model"].items():
        assert torch.equal(tensor, resumed["model"][name]), name


def test_torchrun_two_gloo_processes_average_gradients(world, tmp_path):
    ddp, single = tmp_path / "ddp", tmp_path / "single"
    script = tmp_path / "train.py"
    script.write_text(train_script(world, ddp, evaluate=True, iterations=3, batch_size=1))
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
        str(script),
    ]
    subprocess.run(command, check=True, env=_env(), timeout=240)
    metrics = json.loads((ddp / "metrics.json").read_text())
    assert metrics["processes"] == 2 and metrics["processes_in_sync"]
    # Each process scored its share of the held-out views: the gathered means are one process's.
    one_process = evaluate_held_out(load_run(ddp).model, Stage1Data(world, held_out_per_subject=1))
    assert set(metrics["held_out"]) == {"da", "db"}
    for name, scores in one_process.items():
        shared = metrics["held_out"][name]
        assert shared["views"] == scores["views"] >= 2
        assert shared["psnr"] == pytest.approx(scores["psnr"], abs=1e-6)
        assert shared["ssim"] == pytest.approx(scores["ssim"], abs=1e-7)
    # Two processes with batch 1 see exactly the samples of one process with batch 2.
    train_stage1(
        Stage1Config(
            world, single, tiny_stage1_preset(iterations=3, batch_size=2), progress=False, evaluate=False
        )
    )
    parallel, serial = (
        load_checkpoint(ddp / "checkpoint.pt")["model"],
        load_checkpoint(single / "checkpoint.pt")["model"],
    )
    initial = build_model(
        tiny_stage1_preset(), Stage1Data(world, 1), (), world[0] / "template.obj"
    ).state_dict()
    assert not torch.equal(serial["identity_codes"], initial["identity_codes"])
    # Adam's first steps move each weight by about ±lr whatever the gradient's size, so the few weights
    # whose gradient is ~0 may take either sign from rounding; all others must agree.
    agreeing = sum(int(torch.isclose(parallel[n], t, atol=1e-5, rtol=1e-4).sum()) for n, t in serial.items())
    total = sum(t.numel() for t in serial.values())
    assert agreeing >= 0.999 * total, f"{total - agreeing} of {total} weights differ"


def test_colour_warmup_stores_the_inverse_matrices_and_the_loader_applies_them(world, tmp_path):
    from relightanyone.format.colour_alignment import read_learned_colour
    from relightanyone.model.train.colour_warmup import run_colour_warmup

    metrics = run_colour_warmup(
        world, tmp_path / "run", tiny_stage1_preset(warmup_iterations=6), ("db",), progress=False
    )
    learned = np.asarray(metrics["colour_matrices"]["db"])
    assert not np.allclose(learned, np.eye(3)), "the warm-up did not update the colour matrix"
    stored = read_learned_colour(world[1])
    try:
        assert read_learned_colour(world[0]) is None
        assert np.allclose(stored.matrix @ learned, np.eye(3), atol=1e-6)
        assert {"held_out", "held_out_with_colour_matrix"} <= set(metrics)
        # Every camera trains on some subject (held-out cameras turn per subject), so each has its own:
        # the dataset's matrix with per-channel gains.
        assert set(stored.cameras) == {f"cam{c:02d}" for c in range(4)}
        for camera, render_to_camera in metrics["camera_matrices"]["db"].items():
            assert np.allclose(stored.cameras[camera] @ render_to_camera, np.eye(3), atol=1e-6)
            gains = np.asarray(render_to_camera) @ np.linalg.inv(learned)
            assert np.allclose(gains, np.diag(np.diag(gains)), atol=1e-6) and np.all(np.diag(gains) > 0)
        raw = Stage1Data(world, 1, apply_learned_colour=False)
        aligned = Stage1Data(world, 1)
        for view in aligned.train_views[1][:3]:
            own = stored.for_camera(view.camera)
            expected = np.einsum("ij,jhw->ihw", own, raw.load_view(view)["image"])
            assert np.allclose(aligned.load_view(view)["image"], expected, atol=1e-5)
    finally:
        (world[1] / "colour_alignment.json").unlink()


def test_camera_gains_recover_a_cameras_channel_gains_through_zero_mean_render_error():
    from relightanyone.model.train.colour_warmup import camera_gains

    rng = np.random.default_rng(0)
    skin = rng.uniform(0.2, 0.9, size=(20000, 1)) * np.array([0.8, 0.5, 0.4])  # nearly one colour line
    gains = np.array([1.25, 0.95, 0.8])
    render = skin + rng.normal(0.0, 0.05, size=skin.shape)  # a blurry warm-up render: zero-mean error
    assert np.allclose(camera_gains(render, skin * gains), gains, rtol=0.01)
    # Least squares on the same pixels is pulled toward zero and mixes channels: why gains are used.
    free = np.linalg.lstsq(render, skin * gains, rcond=None)[0].T
    assert np.max(np.abs(np.diag(free) - gains)) > 0.05


def test_render_command_swaps_lighting_codes_without_moving_geometry(trained_run, tmp_path):
    out, _ = trained_run
    runner = CliRunner()
    result = runner.invoke(
        cli,
        [
            "render",
            "stage1",
            str(out),
            "--subject",
            "da/s01",
            "--lighting-code",
            "db",
            "--lighting-grid",
            "--out",
            str(tmp_path / "png"),
        ],
    )
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "png" / "render_report.json").read_text())["subject"]
    assert report["geometry_identical"] is True
    assert report["mean_colour_shift_norm"] > 0
    assert len(report["files"]) == 4 and all(Path(f).is_file() for f in report["files"])
    assert (tmp_path / "png" / "lighting_grid.png").is_file()
    orbit_args = ["--cameras", "orbit", "--orbit-count", "3", "--out", str(tmp_path / "orbit")]
    orbit = runner.invoke(cli, ["render", "stage1", str(out), "--subject", "s00", *orbit_args])
    assert orbit.exit_code != 0 and "several datasets" in orbit.output
    orbit = runner.invoke(cli, ["render", "stage1", str(out), "--subject", "db/s00", *orbit_args])
    assert orbit.exit_code == 0, orbit.output
    assert len(list((tmp_path / "orbit").glob("*.png"))) == 3


def test_train_command_reports_missing_template(tmp_path):
    dataset = write_dataset(tmp_path, "dc", subjects=1, cameras=2, size=16)
    (dataset / "template.obj").unlink()
    result = CliRunner().invoke(
        cli, ["train", "stage1", "--data", str(dataset), "--out", str(tmp_path / "r")]
    )
    assert result.exit_code != 0 and "template.obj" in result.output


def test_no_lighting_code_trains_zero_codes_from_the_same_start(world, tmp_path):
    """The ablation without z_l: codes stay exactly zero, every other weight starts where the normal run
    starts, the run records it, the loaded run decodes alike under every dataset's code, and resuming
    with lighting codes is refused."""
    from relightanyone.model.train.run import decode, load_run

    out = tmp_path / "no-zl"
    args = ["train", "stage1", *[a for d in world for a in ("--data", str(d))], "--iterations", "4"]
    result = CliRunner().invoke(cli, [*args, "--no-lighting-code", "--eval-views", "1", "--out", str(out)])
    assert result.exit_code == 0, result.output
    checkpoint = load_checkpoint(out / "checkpoint.pt")
    assert checkpoint["lighting_code"] is False
    assert json.loads((out / "run.json").read_text())["lighting_code"] is False
    assert torch.count_nonzero(checkpoint["model"]["lighting_codes"]) == 0
    data = Stage1Data(world, held_out_per_subject=1)
    torch.manual_seed(0)
    with_codes = build_model(tiny_stage1_preset(), data, (), data.template_path)
    torch.manual_seed(0)
    without = build_model(tiny_stage1_preset(), data, (), data.template_path, lighting_code=False)
    assert not without.lighting_codes.requires_grad and torch.count_nonzero(with_codes.lighting_codes) > 0
    for name, tensor in with_codes.state_dict().items():
        if name != "lighting_codes":
            assert torch.equal(tensor, without.state_dict()[name]), name
    run = load_run(out)
    assert not run.model.has_lighting_code
    assert torch.equal(decode(run, 0, 0).colours, decode(run, 0, 1).colours)
    resumed = CliRunner().invoke(cli, [*args[:-1], "5", "--eval-views", "1", "--out", str(out)])
    assert resumed.exit_code != 0 and "lighting-code" in resumed.output
