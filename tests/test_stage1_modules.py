"""Stage-1 decoders, Gaussian assembly and the model's code paths (no rasterizer needed)."""

from __future__ import annotations

import math

import pytest
import torch

from relightanyone.model.networks.decoders import ConvUVDecoder, MeshDecoder, upsampling_channels
from relightanyone.model.networks.gaussians import (
    MAX_SCALE,
    MIN_SCALE,
    TexelBinding,
    assemble_gaussians,
    gather_texels,
    geometry_output_bias,
    texel_positions,
    texel_spacing,
)
from relightanyone.model.networks.presets import PRESETS, get_preset
from relightanyone.model.networks.stage1 import Stage1Model


def square_binding(uv_size: int) -> tuple[torch.Tensor, torch.Tensor, TexelBinding]:
    """A unit square (two triangles) in the z=0 plane, its UV map filling the left half of the texture."""
    vertices = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    face_index = torch.zeros(uv_size, uv_size, dtype=torch.long)
    barycentrics = torch.zeros(uv_size, uv_size, 3)
    valid = torch.zeros(uv_size, uv_size, dtype=torch.bool)
    for row in range(uv_size):
        for column in range(uv_size // 2):
            u = (column + 0.5) / (uv_size // 2)
            v = (row + 0.5) / uv_size
            if u >= v:  # triangle 0 (0,0)-(1,0)-(1,1): weights (1-u, u-v, v)
                face_index[row, column], barycentrics[row, column] = 0, torch.tensor([1 - u, u - v, v])
            else:  # triangle 1 (0,0)-(1,1)-(0,1): weights (1-v, u, v-u)
                face_index[row, column], barycentrics[row, column] = 1, torch.tensor([1 - v, u, v - u])
            valid[row, column] = True
    return vertices, faces, TexelBinding.from_maps(face_index, barycentrics, valid, faces)


def test_presets_follow_the_paper_and_reject_bad_sizes():
    paper = get_preset("paper")
    assert (paper.uv_size, paper.z_id_dim, paper.z_l_dim, paper.start_channels) == (1024, 256, 4, 256)
    assert (paper.loss.l1, paper.loss.ssim, paper.loss.geometry, paper.loss.scale) == (10.0, 0.2, 0.4, 0.01)
    assert paper.learning_rate == 1e-3
    assert PRESETS["tiny"].uv_size == 64
    with pytest.raises(ValueError, match="power of two"):
        paper.replace(uv_size=100)
    with pytest.raises(ValueError, match="unknown stage-1 preset"):
        get_preset("huge")
    assert type(paper).from_json(paper.to_json()) == paper


def test_conv_decoder_doubles_from_8x8_to_the_uv_size():
    assert upsampling_channels(1024, 256, 16) == [256, 256, 128, 64, 32, 16, 16]
    decoder = ConvUVDecoder(12, 5, 32, start_channels=24, min_channels=4, output_bias=torch.arange(5.0))
    transposed = [m for m in decoder.layers if isinstance(m, torch.nn.ConvTranspose2d)]
    assert len(transposed) == int(math.log2(32 / 8))
    out = decoder(torch.randn(3, 12))
    assert out.shape == (3, 5, 32, 32)
    # Small last-layer weights: the untrained output sits near the requested bias.
    assert torch.allclose(out.mean(dim=(0, 2, 3)), torch.arange(5.0), atol=0.05)
    assert ConvUVDecoder(4, 2, 8, 8, 4)(torch.randn(1, 4)).shape == (1, 2, 8, 8)


def test_mesh_decoder_starts_at_the_template_and_learns_offsets():
    template = torch.randn(10, 3)
    decoder = MeshDecoder(6, template, hidden=16)
    codes = torch.randn(2, 6)
    assert torch.equal(decoder(codes), template.expand(2, -1, -1))
    target = template + 0.1
    optimizer = torch.optim.Adam(decoder.parameters(), lr=1e-2)
    for _ in range(100):
        optimizer.zero_grad()
        loss = ((decoder(codes) - target) ** 2).mean()
        loss.backward()
        optimizer.step()
    assert loss.item() < 1e-4


def test_texel_positions_are_the_barycentric_points_on_the_mesh():
    vertices, faces, binding = square_binding(8)
    assert binding.count == 8 * 4
    positions = texel_positions(vertices[None], binding)[0]
    # Texel (row, column) of the left half maps to the point (u, v) of the unit square.
    rows, columns = torch.div(binding.valid_index, 8, rounding_mode="floor"), binding.valid_index % 8
    expected = torch.stack(
        [(columns + 0.5) / 4, (rows + 0.5) / 8, torch.zeros_like(rows, dtype=torch.float)], 1
    )
    assert torch.allclose(positions, expected, atol=1e-6)
    maps = torch.arange(2 * 64, dtype=torch.float).view(1, 2, 8, 8)
    gathered = gather_texels(maps, binding)
    assert gathered.shape == (1, 32, 2)
    assert torch.equal(gathered[0, :, 1], maps.view(2, 64)[1, binding.valid_index])


def test_assembled_gaussians_have_valid_ranges_and_sit_on_the_surface():
    vertices, faces, binding = square_binding(8)
    spacing = texel_spacing(vertices, faces, binding.count)
    assert spacing == pytest.approx(math.sqrt(1.0 / 32))
    geometry = geometry_output_bias().view(1, 11, 1, 1).expand(2, 11, 8, 8).clone()
    geometry[1, 7:10] = 50.0  # huge raw scales are clamped
    geometry[1, 0] = 2.0  # an offset of two texel spacings along x
    colour = torch.full((2, 3, 8, 8), -1.0)
    colour[0] = 0.5
    gaussians = assemble_gaussians(geometry, colour, vertices[None].expand(2, -1, -1), binding, spacing)
    base = texel_positions(vertices[None], binding)[0]
    assert torch.allclose(gaussians.means[0], base, atol=1e-6)
    assert torch.allclose(gaussians.means[1, :, 0], base[:, 0] + 2 * spacing, atol=1e-6)
    assert torch.allclose(gaussians.quats.norm(dim=-1), torch.ones(2, 32))
    assert torch.allclose(gaussians.quats[0, :, 0], torch.ones(32))
    assert torch.allclose(gaussians.scales[0], torch.full((32, 3), 0.6 * spacing), atol=1e-5)
    assert torch.allclose(gaussians.scales[1], torch.full((32, 3), MAX_SCALE * spacing))
    assert gaussians.scales.min() >= MIN_SCALE * spacing
    assert ((gaussians.opacities > 0) & (gaussians.opacities < 1)).all()
    assert gaussians.colours[1].eq(0).all() and gaussians.colours[0].eq(0.5).all()


def test_lighting_code_changes_colour_but_never_geometry():
    vertices, faces, binding = square_binding(16)
    preset = get_preset("tiny").replace(uv_size=16, z_id_dim=8, start_channels=16, mesh_hidden=16)
    model = Stage1Model(preset, vertices, binding, subject_count=3, dataset_count=2)
    with torch.no_grad():  # make the colour decoder's response to z_l visible at initialisation
        for parameter in model.colour_decoder.parameters():
            parameter.mul_(50.0)
    subject = torch.tensor([1, 1])
    mesh, gaussians = model(subject, torch.tensor([0, 1]))
    assert torch.equal(mesh[0], mesh[1])
    for name in ("means", "quats", "scales", "opacities"):
        assert torch.equal(getattr(gaussians, name)[0], getattr(gaussians, name)[1]), name
    assert not torch.allclose(gaussians.colours[0], gaussians.colours[1])
    _, warmup = model(subject, torch.tensor([0, 1]), use_lighting=False)
    assert torch.equal(warmup.colours[0], warmup.colours[1])


def test_colour_matrices_apply_only_to_uncalibrated_datasets():
    vertices, faces, binding = square_binding(8)
    preset = get_preset("tiny").replace(uv_size=8, z_id_dim=4, start_channels=8, mesh_hidden=8)
    model = Stage1Model(preset, vertices, binding, 1, 2, uncalibrated=torch.tensor([False, True]))
    with torch.no_grad():
        model.colour_matrices.copy_(torch.diag(torch.tensor([2.0, 1.0, 0.5])).repeat(2, 1, 1))
    images = torch.ones(2, 3, 4, 4)
    out = model.dataset_colour(images, torch.tensor([0, 1]))
    assert torch.equal(out[0], images[0])
    assert torch.allclose(out[1, :, 0, 0], torch.tensor([2.0, 1.0, 0.5]))
