"""Stage-2 network, relit shading and regularisers on small constructed inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from relightanyone.model.networks.gaussians import gather_texels
from relightanyone.model.networks.presets import get_preset
from relightanyone.model.networks.reflectance import (
    INITIAL_ALBEDO,
    INITIAL_VISIBILITY,
    activate_relight_params,
    albedo_prior_loss,
    annealed_weight,
    batch_lights,
    camera_centres,
    monochrome_transfer_loss,
    negative_diffuse_loss,
    normal_residual_loss,
    pattern_light_indices,
    relight,
    view_independent_channels,
)
from relightanyone.model.networks.single_stage import SingleStageModel
from relightanyone.model.networks.stage2 import (
    RelightingUNet,
    Stage2Model,
    head_frame,
    level_channels,
    scatter_texels,
    texel_mesh_normals,
)
from relightanyone.render.camera import look_at_w2c
from relightanyone.render.lights import PointLights, fibonacci_sphere_directions
from relightanyone.render.sh import lambertian_transfer, sh_count

UV_SIZE = 16


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """Template vertices (V, 3) and the texel binding of a UV sphere (one seam) at UV 16²."""
    from helpers.stage1_world import sphere_template_binding

    return sphere_template_binding(tmp_path_factory.mktemp("sphere"), UV_SIZE)


def _random_params(batch: int, count: int, order: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    raw_vi = 0.3 * torch.randn(batch, count, view_independent_channels(order), generator=generator)
    raw_vd = 0.3 * torch.randn(batch, count, 4, generator=generator)
    normals = F.normalize(torch.randn(batch, count, 3, generator=generator), dim=-1)
    return activate_relight_params(raw_vi, raw_vd, normals, order), normals


def test_unet_levels_and_output_shapes_for_every_uv_size():
    assert level_channels(64, 16, 64) == [16, 32, 64, 64]
    assert level_channels(1024, 16, 256) == [16, 32, 64, 128, 256, 256, 256, 256]
    with pytest.raises(ValueError, match="power of two"):
        level_channels(48, 16, 64)
    for size in (8, 16, 32):
        net = RelightingUNet(size, sh_order=3, base_channels=4, max_channels=8)
        vi, vd = net(torch.randn(2, 6, size, size), torch.randn(2, 3))
        assert vi.shape == (2, 3 + 3 * 16 + 1, size, size) and vd.shape == (2, 4, size, size)
    with pytest.raises(ValueError, match="stage-2 input"):
        net(torch.randn(1, 5, 32, 32), torch.randn(1, 3))


def test_stage2_model_gradients_reach_both_decoders_and_view_only_moves_view_dependent_outputs(sphere):
    template, binding = sphere
    centre, radius = head_frame(template)
    model = Stage2Model(binding, centre, radius, sh_order=2, base_channels=8, max_channels=16)
    torch.manual_seed(0)
    with torch.no_grad():  # a trained-looking network: outputs depend on the inputs
        for parameter in model.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    vertices = template[None].repeat(2, 1, 1)
    normals = texel_mesh_normals(vertices, binding)
    positions = torch.randn(2, binding.count, 3) * 0.05
    colours = torch.rand(2, binding.count, 3)
    cameras = torch.tensor([[0.0, 0.0, 0.5], [0.5, 0.0, 0.0]])
    params = model(colours, positions, normals, cameras)
    count = binding.count
    assert params.albedo.shape == (2, count, 3) and params.transfer.shape == (2, count, 3, 9)
    assert params.roughness.shape == params.visibility.shape == (2, count)
    assert torch.allclose(params.normals.norm(dim=-1), torch.ones(2, count), atol=1e-5)
    loss = (
        params.albedo.sum()
        + params.transfer.sum()
        + params.roughness.sum()
        + params.visibility.sum()
        + params.normals.sum()
    )
    loss.backward()
    for name in (
        "unet.encoder.stem.0.weight",
        "unet.view_independent.output.weight",
        "unet.view_dependent.output.weight",
        "unet.view_dependent.bottleneck.0.weight",
    ):
        gradient = dict(model.named_parameters())[name].grad
        assert gradient is not None and gradient.abs().sum() > 0, name
    with torch.no_grad():
        other_view = model(colours, positions, normals, cameras.flip(0))
    assert torch.equal(other_view.albedo, params.albedo.detach()) and torch.equal(
        other_view.transfer, params.transfer.detach()
    )
    assert not torch.allclose(other_view.visibility, params.visibility.detach())


def test_untrained_outputs_are_rgca_defaults_over_a_lambertian_transfer():
    order = 3
    normals = F.normalize(torch.randn(1, 50, 3), dim=-1)
    from relightanyone.model.networks.reflectance import (
        view_dependent_output_bias,
        view_independent_output_bias,
    )

    params = activate_relight_params(
        view_independent_output_bias(order).expand(1, 50, -1),
        view_dependent_output_bias().expand(1, 50, -1),
        normals,
        order,
    )
    assert torch.allclose(params.albedo, torch.full_like(params.albedo, INITIAL_ALBEDO))
    assert torch.allclose(params.visibility, torch.full_like(params.visibility, INITIAL_VISIBILITY))
    assert torch.allclose(params.roughness, torch.full_like(params.roughness, 0.1))
    assert torch.allclose(
        params.transfer, lambertian_transfer(normals, order)[:, :, None].expand(-1, -1, 3, -1)
    )
    assert torch.allclose(params.normals, normals) and params.sh_order == order


def test_scatter_then_gather_returns_the_texel_values_and_zeros_elsewhere(sphere):
    _, binding = sphere
    values = torch.randn(2, binding.count, 5)
    maps = scatter_texels(values, binding)
    assert maps.shape == (2, 5, UV_SIZE, UV_SIZE)
    assert torch.equal(gather_texels(maps, binding), values)
    invalid = torch.ones(UV_SIZE * UV_SIZE, dtype=torch.bool)
    invalid[binding.valid_index] = False
    assert maps.reshape(2, 5, -1)[:, :, invalid].abs().sum() == 0


def test_full_on_relit_colour_is_the_sum_of_the_olat_relit_colours():
    order, count, light_count = 3, 200, 5
    params, _ = _random_params(1, count, order)
    positions = torch.randn(1, count, 3) * 0.05
    camera = torch.tensor([[0.1, 0.05, 0.6]])
    rig = PointLights(fibonacci_sphere_directions(light_count) * 1.2, torch.rand(light_count, 3) + 0.5)
    centre = torch.zeros(3)
    full = relight(params, positions, camera, rig.positions[None], rig.intensities[None], centre)
    singles = [
        relight(
            params,
            positions,
            camera,
            rig.positions[k : k + 1][None],
            rig.intensities[k : k + 1][None],
            centre,
        )
        for k in range(light_count)
    ]
    diffuse_sum = sum(s.diffuse for s in singles)
    specular_sum = sum(s.specular for s in singles)
    assert torch.allclose(full.diffuse, diffuse_sum, rtol=1e-4, atol=1e-6)
    assert torch.allclose(full.specular, specular_sum, rtol=1e-4, atol=1e-6)
    assert full.specular.abs().sum() > 0 and full.diffuse.abs().sum() > 0
    # The final colour clamps negative diffuse only; with a transfer whose diffuse cannot go negative (a
    # positive constant term) the final colours add up as well.
    transfer = torch.zeros_like(params.transfer)
    transfer[..., 0] = params.transfer[..., 0].abs()
    positive = type(params)(**{**vars(params), "transfer": transfer})
    full = relight(positive, positions, camera, rig.positions[None], rig.intensities[None], centre)
    colour_sum = sum(
        relight(
            positive,
            positions,
            camera,
            rig.positions[k : k + 1][None],
            rig.intensities[k : k + 1][None],
            centre,
        ).colour
        for k in range(light_count)
    )
    assert torch.allclose(full.colour, colour_sum, rtol=1e-4, atol=1e-6)
    # The same sum through padded batching: one OLAT light per sample, padding lights contribute nothing.
    positions_b, intensities_b = batch_lights(
        rig, [[k] for k in range(light_count)] + [list(range(light_count))]
    )
    batched = relight(
        type(params)(**{k: v.expand(light_count + 1, *v.shape[1:]) for k, v in vars(params).items()}),
        positions.expand(light_count + 1, -1, -1),
        camera.expand(light_count + 1, -1),
        positions_b,
        intensities_b,
        centre,
    )
    assert torch.allclose(batched.diffuse[:-1].sum(0), batched.diffuse[-1], rtol=1e-4, atol=1e-6)
    assert torch.allclose(batched.specular[:-1].sum(0), batched.specular[-1], rtol=1e-4, atol=1e-6)


def test_lambertian_default_matches_a_point_light_and_albedo_only_scales_diffuse():
    normals = torch.tensor([[[0.0, 0.0, 1.0]]])
    order = 8
    view_independent = torch.zeros(1, 1, view_independent_channels(order))
    view_independent[..., :3] = math.log(math.expm1(0.5))
    view_dependent = torch.tensor([[[-30.0, 0.0, 0.0, 0.0]]])  # visibility ~ 0: diffuse only
    params = activate_relight_params(view_independent, view_dependent, normals, order)
    light = torch.tensor([[[0.0, 0.0, 2.0]]])
    relit = relight(
        params,
        torch.zeros(1, 1, 3),
        torch.tensor([[0.0, 0.0, 1.0]]),
        light,
        torch.full((1, 1, 3), 4.0),
        torch.zeros(3),
    )
    # Head-on light of intensity 4 at 2 m: irradiance 1, radiance albedo / π (truncated SH at order 8).
    assert torch.allclose(relit.diffuse, torch.full((1, 1, 3), 0.5 / math.pi), rtol=0.03)
    assert relit.specular.abs().max() < 1e-6


def test_negative_diffuse_and_monochrome_losses_are_zero_exactly_when_they_should_be():
    diffuse = torch.rand(2, 30, 3)
    assert torch.equal(negative_diffuse_loss(diffuse), torch.zeros(2))
    diffuse[1, 4, 2] = -0.5
    loss = negative_diffuse_loss(diffuse)
    assert loss[0] == 0 and torch.isclose(loss[1], torch.tensor(0.25 / 90))
    grey = torch.randn(2, 30, 1, 16).expand(-1, -1, 3, -1)
    assert torch.allclose(monochrome_transfer_loss(grey), torch.zeros(2), atol=1e-12)
    tinted = grey.clone()
    tinted[0, :, 0] += 0.3
    mono = monochrome_transfer_loss(tinted)
    assert mono[0] > 0 and mono[1].abs() < 1e-12
    # Channel offsets (+0.2, -0.1, -0.1) from the mean give a mean square of 0.02.
    assert torch.isclose(mono[0], torch.tensor(0.02), rtol=1e-4)
    assert torch.equal(normal_residual_loss(torch.zeros(1, 4, 3)), torch.zeros(1))
    assert torch.isclose(normal_residual_loss(torch.full((1, 4, 3), 0.5))[0], torch.tensor(0.75))
    prior = torch.rand(30, 3)
    assert (
        albedo_prior_loss(prior[None], prior)[0] == 0 and albedo_prior_loss(prior[None] + 0.1, prior)[0] > 0
    )


def test_annealing_schedules_match_the_paper_endpoints():
    assert annealed_weight(0, 1.0, 0.0, 100) == 1.0
    assert annealed_weight(50, 1.0, 0.0, 100) == pytest.approx(0.5)
    assert annealed_weight(100, 1.0, 0.0, 100) == 0.0 and annealed_weight(10**6, 1.0, 0.0, 100) == 0.0
    assert annealed_weight(0, 10.0, 0.01, 100) == 10.0
    assert annealed_weight(50, 10.0, 0.01, 100) == pytest.approx(math.sqrt(10.0 * 0.01))
    assert annealed_weight(200, 10.0, 0.01, 100) == 0.01


def test_pattern_lights_cameras_and_errors():
    named = {"olat-000": 0, "olat-001": 1, "olat-002": 2}
    assert pattern_light_indices("full", named, 3, "d1") == [0, 1, 2]
    assert pattern_light_indices("olat-002", named, 3, "d1") == [2]
    assert pattern_light_indices("olat-001", {}, 3, "d1") == [1]
    with pytest.raises(ValueError, match="d1: image pattern 'olat-007'"):
        pattern_light_indices("olat-007", named, 3, "d1")
    with pytest.raises(ValueError, match="sunset"):
        pattern_light_indices("sunset", named, 3, "d1")
    eye = [0.3, -0.2, 0.9]
    w2c = torch.tensor(look_at_w2c(eye, np.zeros(3), [0.0, 1.0, 0.0]), dtype=torch.float32)[None]
    assert torch.allclose(camera_centres(w2c), torch.tensor([eye]), atol=1e-6)


def test_single_stage_model_decodes_geometry_and_reflectance_with_gradients(sphere):
    template, binding = sphere
    preset = get_preset("tiny").replace(
        uv_size=UV_SIZE, z_id_dim=8, start_channels=16, min_channels=8, mesh_hidden=16
    )
    model = SingleStageModel(preset, sh_order=3, template_vertices=template, binding=binding, subject_count=3)
    cameras = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.3, 0.4]])
    vertices, gaussians, params = model(torch.tensor([0, 2]), cameras)
    assert vertices.shape == (2, template.shape[0], 3) and gaussians.means.shape == (2, binding.count, 3)
    assert params.transfer.shape == (2, binding.count, 3, sh_count(3))
    assert torch.allclose(gaussians.colours, params.albedo)
    (params.albedo.sum() + params.visibility.sum() + gaussians.means.sum()).backward()
    assert model.identity_codes.grad[[0, 2]].abs().sum() > 0 and model.identity_codes.grad[1].abs().sum() == 0
    assert model.view_decoder.to_grid.weight.grad.abs().sum() > 0


def test_full_on_rig_uses_the_recorded_full_on_intensities():
    from relightanyone.render.lights import full_on_rig_from_table, olat_rig_from_table

    table = {
        "index": [1, 0],
        "position_m": [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
        "intensity_rgb": [[2.0, 2.0, 2.0], [4.0, 4.0, 4.0]],
        "full_on_intensity_rgb": [[0.1, 0.1, 0.1], [0.2, 0.3, 0.4]],
    }
    rig = olat_rig_from_table(table)
    full = full_on_rig_from_table(table, rig)
    assert torch.equal(full.positions, rig.positions)  # same lights, in index order
    assert torch.allclose(full.intensities, torch.tensor([[0.2, 0.3, 0.4], [0.1, 0.1, 0.1]]))
    unknown = dict(table, full_on_intensity_rgb=[None, None])
    assert full_on_rig_from_table(unknown, rig) is rig
    with pytest.raises(ValueError, match="negative"):
        full_on_rig_from_table(dict(table, full_on_intensity_rgb=[[-1.0, 0, 0], [0, 0, 0]]), rig)
