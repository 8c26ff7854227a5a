"""The 3D Gaussian Splatting PLY writer and reader (relightanyone.model.fit.ply)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from relightanyone.model.fit.ply import (
    SH_C0,
    gaussian_ply_properties,
    read_gaussian_ply,
    sh_rest_count,
    write_gaussian_ply,
)


def _gaussians(count: int = 6, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    quats = torch.randn(count, 4, generator=generator)
    return {
        "means": torch.randn(count, 3, generator=generator) * 0.05,
        "quats": quats * 3.0,  # not unit: the writer normalizes
        "scales": torch.rand(count, 3, generator=generator) * 0.02 + 0.002,
        "opacities": torch.rand(count, generator=generator) * 0.9 + 0.05,
        "colours": torch.rand(count, 3, generator=generator) * 1.2,
    }


def test_file_layout_is_the_reference_3dgs_vertex_element(tmp_path):
    gaussians = _gaussians()
    gaussians["colours"][0] = torch.tensor([0.5, 1.0, 0.0])
    gaussians["opacities"][0] = 0.5
    gaussians["scales"][0] = torch.tensor([1.0, np.e, 0.5])
    gaussians["quats"][0] = torch.tensor([2.0, 0.0, 0.0, 0.0])
    path = write_gaussian_ply(tmp_path / "a.ply", **gaussians)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert not list(tmp_path.glob(".*.tmp"))
    ply = PlyData.read(str(path))
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(45)]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == expected == gaussian_ply_properties(3)
    assert all(p.val_dtype in ("f4", "float32", "float") for p in vertex.properties), vertex.properties
    data = vertex.data
    assert len(data) == 6
    # f_dc = (c - 0.5) / C0, opacity = logit, scale = log, rot = unit w x y z.
    np.testing.assert_allclose(
        [data["f_dc_0"][0], data["f_dc_1"][0], data["f_dc_2"][0]], [0.0, 0.5 / SH_C0, -0.5 / SH_C0], rtol=1e-6
    )
    assert data["opacity"][0] == pytest.approx(0.0, abs=1e-7)
    np.testing.assert_allclose(
        [data["scale_0"][0], data["scale_1"][0], data["scale_2"][0]], [0.0, 1.0, np.log(0.5)], atol=1e-6
    )
    np.testing.assert_allclose([data[f"rot_{i}"][0] for i in range(4)], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(data["x"], gaussians["means"][:, 0].numpy())
    rest = np.stack([data[f"f_rest_{i}"] for i in range(45)])
    normals = np.stack([data[n] for n in ("nx", "ny", "nz")])
    assert not rest.any() and not normals.any()


def test_read_back_gives_the_activated_parameters(tmp_path):
    gaussians = _gaussians(32, seed=1)
    gaussians["opacities"][:2] = torch.tensor([1.0, 0.0])  # stored as finite logits just inside (0, 1)
    path = write_gaussian_ply(tmp_path / "b.ply", **gaussians)
    read = read_gaussian_ply(path)
    torch.testing.assert_close(read["means"], gaussians["means"])
    torch.testing.assert_close(
        read["quats"], gaussians["quats"] / gaussians["quats"].norm(dim=1, keepdim=True)
    )
    torch.testing.assert_close(read["scales"], gaussians["scales"], rtol=1e-6, atol=0)
    torch.testing.assert_close(read["opacities"], gaussians["opacities"], rtol=0, atol=1e-6)
    torch.testing.assert_close(read["colours"], gaussians["colours"], rtol=0, atol=1e-6)
    assert read["sh_rest"].shape == (32, 15, 3) and not read["sh_rest"].any()
    assert np.isfinite(PlyData.read(str(path))["vertex"].data["opacity"]).all()


def test_read_back_renders_the_same_image(tmp_path):
    from relightanyone.render.camera import look_at_w2c
    from relightanyone.render.rasterize import rasterize

    gaussians = _gaussians(64, seed=2)
    gaussians["colours"] = gaussians["colours"].clamp(max=1.0)
    size = 20
    K = torch.tensor([[[40.0, 0.0, 9.5], [0.0, 40.0, 9.5], [0.0, 0.0, 1.0]]])
    w2c = torch.tensor(
        look_at_w2c(np.array([0.1, 0.05, 0.4]), np.zeros(3), np.array([0.0, 1.0, 0.0])), dtype=torch.float32
    )[None]

    def render(g):
        return rasterize(
            g["means"], g["quats"], g["scales"], g["opacities"], g["colours"], w2c, K, size, size
        )[0]

    read = read_gaussian_ply(write_gaussian_ply(tmp_path / "r.ply", **gaussians))
    expected = render(gaussians)
    assert float(expected.amax()) > 0.1
    torch.testing.assert_close(render(read), expected, rtol=0, atol=1e-5)


def test_degree_zero_has_no_rest_bands_and_other_tools_rest_bands_are_channel_major(tmp_path):
    path = write_gaussian_ply(tmp_path / "dc.ply", sh_degree=0, **_gaussians(3))
    assert sh_rest_count(0) == 0 and not any(
        p.name.startswith("f_rest") for p in PlyData.read(str(path))["vertex"].properties
    )
    assert read_gaussian_ply(path)["sh_rest"].shape == (3, 0, 3)
    # A degree-1 file as the reference trainer writes it: f_rest_{c * 3 + k} is band k of channel c.
    names = gaussian_ply_properties(1)
    data = np.zeros(2, dtype=[(n, "<f4") for n in names])
    data["rot_0"] = 1.0
    for i in range(9):
        data[f"f_rest_{i}"] = i + 1
    PlyData([PlyElement.describe(data, "vertex")], byte_order="<").write(str(tmp_path / "deg1.ply"))
    rest = read_gaussian_ply(tmp_path / "deg1.ply")["sh_rest"]
    assert rest.shape == (2, 3, 3)
    torch.testing.assert_close(rest[0], torch.tensor([[1.0, 4.0, 7.0], [2.0, 5.0, 8.0], [3.0, 6.0, 9.0]]))
    with pytest.raises(ValueError, match="sh_degree"):
        sh_rest_count(4)


def test_bad_inputs_name_the_file_and_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        read_gaussian_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"this is not a ply file")
    with pytest.raises(ValueError, match="junk.ply"):
        read_gaussian_ply(tmp_path / "junk.ply")
    points = np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(points, "vertex")]).write(str(tmp_path / "cloud.ply"))
    with pytest.raises(ValueError, match=r"cloud.ply.*f_dc_0"):
        read_gaussian_ply(tmp_path / "cloud.ply")
    gaussians = _gaussians(2)
    with pytest.raises(ValueError, match="scales must be positive"):
        write_gaussian_ply(tmp_path / "x.ply", **(gaussians | {"scales": -gaussians["scales"]}))
    with pytest.raises(ValueError, match=r"colours must be \(2, 3\), got \(3, 3\)"):
        write_gaussian_ply(tmp_path / "x.ply", **(gaussians | {"colours": torch.zeros(3, 3)}))
    with pytest.raises(ValueError, match="opacities must be in"):
        write_gaussian_ply(tmp_path / "x.ply", **(gaussians | {"opacities": torch.full((2,), 1.5)}))
    assert not (tmp_path / "x.ply").exists()
