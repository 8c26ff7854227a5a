"""Fitting an unseen subject (inversion, finetuning with the locality regulariser) and the avatar file.

The world: an OLAT dataset of Lambertian spheres (the stage-1 test template) under a four-light rig, seen
by four cameras. Subjects s00 and s01 are training subjects; s02 (a larger, differently coloured sphere,
split "test") is never trained on and is fitted from its images under an unknown lighting: the rig with
other RGB intensities per light.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.sphere_world import LIGHTS, RIG_INTENSITY, SIZE, build_sphere_world

from relightanyone.errors import InputError
from relightanyone.model.fit.avatar import FittedAvatar
from relightanyone.model.fit.fitter import (
    DatasetLitFitter,
    FitSettings,
    Fitter,
    fit_subject,
    load_relightable_model,
    locality_codes,
    locality_loss,
)
from relightanyone.model.fit.views import load_fit_views
from relightanyone.model.networks.render import render_views
from relightanyone.render.camera import Cameras
from relightanyone.render.lights import PointLights

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    """The OLAT dataset, a stage-1 run on its training subjects and a stage-2 run on top."""
    return build_sphere_world(tmp_path_factory.mktemp("fit-world"))


def _fitter(world, **settings) -> Fitter:
    model = load_relightable_model(world["stage1"], world["stage2"])
    views = load_fit_views(world["data"], "s02")
    defaults = dict(
        inversion_iterations=0,
        finetune_iterations=0,
        inversion_lr=5e-2,
        finetune_lr=3e-3,
        views_per_step=2,
        progress=False,
    )
    return Fitter(model, views, FitSettings(**(defaults | settings)))


@pytest.fixture(scope="module")
def avatar(world) -> FittedAvatar:
    settings = FitSettings(inversion_iterations=4, finetune_iterations=2, views_per_step=2, progress=False)
    return fit_subject(
        world["stage1"],
        world["stage2"],
        world["data"],
        "s02",
        settings=settings,
        out=world["root"] / "s02.avatar",
    )


def test_views_of_an_unseen_subject_are_read_with_cameras_and_tracked_mesh(world):
    views = load_fit_views(world["data"], "s02", cameras=["cam02"])
    assert (
        len(views) == 1
        and views.images.shape == (1, 3, SIZE, SIZE)
        and views.masks.shape == (1, 1, SIZE, SIZE)
    )
    assert (
        views.tracked_vertices is not None
        and views.frame == 0
        and views.keys == ["olat/s02/000000/cam02/full"]
    )
    half = load_fit_views(world["data"], "s02", image_scale=0.5)
    assert half.images.shape == (4, 3, SIZE // 2, SIZE // 2)
    # Pixel centres stay put: c' = (c + 0.5) s - 0.5.
    assert float(half.K[0, 0, 2]) == pytest.approx(((SIZE - 1) / 2 + 0.5) * 0.5 - 0.5)
    assert float(half.K[0, 0, 0]) == pytest.approx(2.2 * SIZE * 0.5)
    with pytest.raises(ValueError, match="no subject 'nobody'"):
        load_fit_views(world["data"], "nobody")
    with pytest.raises(ValueError, match="no camera"):
        load_fit_views(world["data"], "s02", cameras=["cam99"])
    with pytest.raises(ValueError, match="no rows with pattern 'olat-000'"):
        load_fit_views(world["data"], "s02", pattern="olat-000")


def test_inversion_starts_at_the_mean_code_and_lowers_the_photometric_loss(world):
    fitter = _fitter(world)
    model = fitter.model
    assert torch.equal(fitter.z_id.detach()[0], model.stage1.identity_codes.detach().mean(dim=0))
    assert torch.equal(fitter.light_intensities().detach(), model.rig.intensities)
    weights_before = {k: v.clone() for k, v in model.stage1.state_dict().items()}
    before = fitter.evaluate()
    fitter.invert(8)
    after = fitter.evaluate()
    assert after["l1"] < 0.8 * before["l1"], (before, after)
    assert not torch.equal(fitter.z_id.detach()[0], model.stage1.identity_codes.detach().mean(dim=0))
    # Inversion moves only the code and the lighting: no stage-1 or stage-2 weight changes.
    assert all(torch.equal(v, fitter.stage1.state_dict()[k]) for k, v in weights_before.items())
    assert all(not p.requires_grad for p in fitter.stage2.parameters())


def test_every_rig_light_intensity_gets_a_gradient(world):
    fitter = _fitter(world)
    total, terms = fitter.inversion_loss(list(range(len(fitter.views))))
    total.backward()
    gradient = fitter.log_intensities.grad
    assert gradient is not None and gradient.shape == (4, 3)
    assert bool((gradient.abs() > 0).all()), gradient
    assert fitter.z_id.grad is not None and float(fitter.z_id.grad.abs().sum()) > 0
    assert {"l1", "ssim", "geometry", "identity", "total"} <= set(terms)
    # The lights move away from the calibrated rig towards the scene lighting (light 1 is dimmed most).
    fitter.invert(4)
    intensities = fitter.light_intensities().detach()
    assert not torch.allclose(intensities, fitter.model.rig.intensities)


def test_lighting_prior_holds_the_split_between_reflectance_and_light(world):
    # Images fix only reflectance × light: the prior keeps the scene light near the full-on rig, so the
    # brightness the fit needs goes to the subject, not to the lights.
    drift = {}
    for weight in (0.0, 100.0):
        fitter = _fitter(world, lighting_prior_weight=weight)
        start = fitter.log_intensities.detach().clone()
        fitter.invert(6)
        drift[weight] = float((fitter.log_intensities.detach() - start).abs().max())
        assert fitter.history["inversion"][-1]["lighting_prior"] >= 0
    assert drift[100.0] < 0.5 * drift[0.0]


def _finetuned(world, locality_weight: float) -> tuple[Fitter, float, float]:
    """Finetune from the same inversion; returns the fitter, its weight change and its change on training codes."""
    fitter = _fitter(world, locality_codes=2)
    fitter.invert(3)
    initial = [p.detach().clone() for p in fitter.decoder_parameters()]
    fitter.finetune(8, locality_weight=locality_weight)
    weight_change = float(
        torch.sqrt(
            sum(
                ((p.detach() - q) ** 2).sum()
                for p, q in zip(fitter.decoder_parameters(), initial, strict=True)
            )
        )
    )
    codes = fitter.model.training_codes
    z_l = fitter.z_l.expand(codes.shape[0], -1)
    with torch.no_grad():
        change = float(
            locality_loss(
                fitter.stage1.decode(codes, z_l),
                fitter.reference.decode(codes, z_l),
                fitter.spacing,
            ).mean()
        )
    return fitter, weight_change, change


def test_locality_regulariser_keeps_finetuning_local(world):
    free, free_weights, free_change = _finetuned(world, 0.0)
    local, local_weights, local_change = _finetuned(world, 1.0)
    assert "locality" in local.history["finetune"][-1] and "locality" not in free.history["finetune"][-1]
    assert local_weights < free_weights, (local_weights, free_weights)
    assert local_change < free_change, (local_change, free_change)
    # Finetuning froze the pivot and stage 2, and left the reference (the loaded model) untouched.
    assert not local.z_id.requires_grad and not local.log_intensities.requires_grad
    assert local.reference is local.model.stage1 and all(
        not p.requires_grad for p in local.reference.parameters()
    )


def test_avatar_save_load_round_trip_renders_identical_images(world, avatar, tmp_path):
    path = world["root"] / "s02.avatar"
    assert path.is_file() and not list(path.parent.glob(".*.tmp"))
    loaded = FittedAvatar.load(path)
    assert loaded.metadata["subject"] == "s02" and loaded.metadata["iterations"] == {
        "inversion": 4,
        "finetune": 2,
    }
    assert loaded.metadata["mesh"] == "tracked" and loaded.tracked_vertices is not None
    cameras = _cameras(world)
    for lighting in (avatar.scene_lights(), avatar.olat(2)):
        assert torch.equal(avatar.relight(cameras, lighting), loaded.relight(cameras, lighting))
    assert torch.equal(loaded.scene_intensities, avatar.scene_intensities)
    assert torch.equal(
        loaded.to("cpu").relight(cameras, avatar.olat(1)), avatar.relight(cameras, avatar.olat(1))
    )
    (tmp_path / "bad.avatar").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="bad.avatar"):
        FittedAvatar.load(tmp_path / "bad.avatar")
    with pytest.raises(FileNotFoundError, match="missing.avatar"):
        FittedAvatar.load(tmp_path / "missing.avatar")


def _cameras(world) -> Cameras:
    views = load_fit_views(world["data"], "s02")
    return Cameras.create(views.K.double(), views.w2c.double(), SIZE, SIZE)


def test_olat_light_and_point_light_at_the_same_position_give_the_same_image(world, avatar):
    cameras = _cameras(world)
    olat = avatar.relight(cameras, avatar.olat(0))
    point = avatar.relight(
        cameras, PointLights(torch.tensor(LIGHTS[:1], dtype=torch.float32), torch.full((1, 3), RIG_INTENSITY))
    )
    assert olat.shape == (4, 3, SIZE, SIZE) and float(olat.max()) > 0
    torch.testing.assert_close(olat, point, rtol=0, atol=1e-6)
    # Linearity through the whole path: twice the intensity, twice the image.
    doubled = avatar.relight(cameras, avatar.olat(0).scaled(2.0))
    torch.testing.assert_close(doubled, 2 * olat, rtol=1e-4, atol=1e-6)
    relit = avatar.gaussians(avatar.olat(0), cameras[0])
    assert set(relit) == {"means", "quats", "scales", "opacities", "colours"}
    assert relit["colours"].shape == (avatar.gaussian_count, 3) and bool((relit["colours"] >= 0).all())


def test_envmap_relight_from_an_exr_file(world, avatar, tmp_path):
    from relightanyone.render.envmap import latlong_directions, save_envmap

    directions = latlong_directions(16, 32)
    # A warm sky in front of the face over a dim ambient.
    env = (
        0.05
        + 2.0 * (directions[..., 2].clamp(min=0) ** 4)[None] * torch.tensor([1.0, 0.8, 0.6])[:, None, None]
    )
    path = tmp_path / "studio.exr"
    save_envmap(path, env)
    cameras = _cameras(world)
    lit = avatar.relight(cameras, path)
    assert lit.shape == (4, 3, SIZE, SIZE) and bool(torch.isfinite(lit).all()) and float(lit.min()) >= 0
    assert float(lit.mean()) > 0
    dark = avatar.relight(cameras, torch.zeros(3, 16, 32))
    assert float(dark.abs().max()) == 0.0
    brighter = avatar.relight(cameras, 2 * env)
    assert float(brighter.sum()) > float(lit.sum())
    with pytest.raises(ValueError, match="environment map"):
        avatar.relight(cameras, torch.zeros(16, 32))


def test_locality_codes_lie_between_the_fit_and_training_codes():
    fitted = torch.zeros(1, 3)
    training = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    codes = locality_codes(fitted, training, 64, 0.5, np.random.default_rng(0))
    assert codes.shape == (64, 3)
    # Every code is t · (a training code) with t in [0.5, 1]: on one axis, between half and all of it.
    on_first = codes[:, 1] == 0
    assert bool(on_first.any()) and bool((~on_first).any())
    assert bool(((codes[on_first, 0] >= 0.5) & (codes[on_first, 0] <= 1.0)).all())
    assert bool(((codes[~on_first, 1] >= 1.0) & (codes[~on_first, 1] <= 2.0)).all())
    assert torch.equal(codes, locality_codes(fitted, training, 64, 0.5, np.random.default_rng(0)))
    with pytest.raises(ValueError, match="locality_min_fraction"):
        FitSettings(locality_min_fraction=1.5)


def test_single_image_fit_without_a_tracked_mesh(world):
    model = load_relightable_model(world["stage1"], world["stage2"])
    views = load_fit_views(world["data"], "s02", cameras=["cam01"])
    views.tracked_vertices = None
    fitter = Fitter(model, views, FitSettings(inversion_iterations=2, finetune_iterations=1, progress=False))
    fitter.invert()
    fitter.finetune()
    assert "geometry" not in fitter.history["inversion"][-1] and "locality" in fitter.history["finetune"][-1]
    single = fitter.avatar()
    assert single.metadata["mesh"] == "decoded" and single.tracked_vertices is None
    assert single.metadata["cameras"] == ["cam01"] and single.means.shape == (model.stage1.binding.count, 3)


def test_dataset_lit_fit_renders_as_stage1_under_the_input_code_and_estimates_no_light(world):
    model = load_relightable_model(world["stage1"], world["stage2"])
    assert torch.equal(model.dataset_lighting_code("olat"), model.lighting_code)
    with pytest.raises(InputError, match=r"dataset 'other'.*\['olat'\]"):
        model.dataset_lighting_code("other")
    views = load_fit_views(world["data"], "s02")
    settings = FitSettings(inversion_iterations=6, finetune_iterations=2, inversion_lr=5e-2, progress=False)
    # Any code: the fit must render the input views under exactly the code it is given.
    code = model.lighting_code + 0.5
    fitter = DatasetLitFitter(model, views, code, settings)
    image, alpha, _, _ = fitter.render([0, 1])
    with torch.no_grad():
        _, gaussians = model.stage1.decode(fitter.z_id, code[None])
        expected, expected_alpha = render_views(gaussians, views.K[:2], views.w2c[:2], SIZE, SIZE)
    torch.testing.assert_close(image.detach(), expected)
    torch.testing.assert_close(alpha.detach(), expected_alpha)
    before = fitter.evaluate()
    fitter.invert()
    assert fitter.evaluate()["l1"] < before["l1"]
    assert "lighting_prior" not in fitter.history["inversion"][-1]
    assert torch.equal(fitter.light_intensities().detach(), (model.full_on_rig or model.rig).intensities)
    fitter.finetune()
    avatar = fitter.avatar()
    # The avatar is the OLAT-code decode of the fitted subject, relit by stage 2 like any other fit.
    with torch.no_grad():
        _, olat_gaussians = fitter.stage1.decode(fitter.z_id, model.lighting_code[None])
        _, input_gaussians = fitter.stage1.decode(fitter.z_id, code[None])
    torch.testing.assert_close(avatar.colours, olat_gaussians.colours[0])
    assert not torch.allclose(avatar.colours, input_gaussians.colours[0])


def test_fit_command_writes_one_avatar_per_held_out_subject_and_keeps_it(world, tmp_path):
    from click.testing import CliRunner

    from relightanyone.cli import cli

    args = ["fit", "--stage1", str(world["stage1"]), "--stage2", str(world["stage2"]), "--data", str(world["data"]),
            "--inversion-iterations", "2", "--finetune-iterations", "1", "--views-per-step", "2",
            "--threads", "1", "--out", str(tmp_path)]  # fmt: skip
    first = CliRunner().invoke(cli, args)
    assert first.exit_code == 0, first.output
    avatar = FittedAvatar.load(tmp_path / "s02.avatar")  # the only test-split subject
    assert avatar.metadata["subject"] == "s02" and sorted(p.name for p in tmp_path.glob("*.avatar")) == [
        "s02.avatar"
    ]
    assert "s02" in (tmp_path / "fit_report.json").read_text()
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 0 and "kept" in again.output
    missing = CliRunner().invoke(cli, [*args[:7], "--subject", "nobody", "--out", str(tmp_path / "x")])
    assert missing.exit_code != 0 and "nobody" in missing.output


def test_fit_command_fits_inputs_under_their_dataset_code(world, tmp_path):
    from click.testing import CliRunner

    from relightanyone.cli import cli

    args = ["fit", "--stage1", str(world["stage1"]), "--stage2", str(world["stage2"]), "--data", str(world["data"]),
            "--subject", "s02", "--camera", "cam01", "--inversion-iterations", "2", "--finetune-iterations", "1",
            "--threads", "1", "--input-lighting", "dataset", "--out", str(tmp_path)]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    avatar = FittedAvatar.load(tmp_path / "s02.avatar")
    assert avatar.metadata["input_lighting"] == "dataset"
    # No light is estimated: the avatar keeps the OLAT dataset's full-on light as its scene lighting.
    model = load_relightable_model(world["stage1"], world["stage2"])
    assert torch.equal(avatar.scene_intensities, (model.full_on_rig or model.rig).intensities)
    wrong = CliRunner().invoke(cli, [*args[:-4], "--input-lighting", "studio", "--out", str(tmp_path / "x")])
    assert wrong.exit_code != 0 and "studio" in wrong.output
