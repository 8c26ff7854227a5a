"""Degenerate and bad inputs, backend selection and the compiled-kernel fallback."""

from __future__ import annotations

import warnings

import pytest
import torch
from helpers.raster_scenes import GAUSSIAN_INPUTS, random_scene

from relightanyone.render import rasterize_cpp
from relightanyone.render.rasterize import rasterize, select_backend

BACKENDS = ["dense", "torch", "cpp"]
BACKGROUND = torch.tensor([0.25, 0.5, 0.75])


def assert_empty(out, C, H, W):
    out = type(out)(*(t.detach() for t in out))
    assert (
        out.features.shape == (C, 3, H, W)
        and out.alpha.shape == (C, 1, H, W)
        and out.depth.shape == (C, 1, H, W)
    )
    torch.testing.assert_close(out.features, BACKGROUND.view(1, 3, 1, 1).expand(C, 3, H, W))
    assert float(out.alpha.abs().max()) == 0.0
    assert float(out.depth.abs().max()) == 0.0


def scene32(**kwargs):
    return random_scene(dtype=torch.float32, **kwargs)


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_gaussians_gives_background(backend):
    s = scene32(n=0)
    assert_empty(rasterize(**s, background=BACKGROUND, backend=backend), 2, 29, 37)


@pytest.mark.parametrize("backend", BACKENDS)
def test_all_behind_camera_gives_background_and_finite_gradients(backend):
    s = scene32(n=20)
    s["means"] = s["means"].clone()
    s["means"][:, 2] += 1.5  # world z in [1.35, 1.65]
    s["w2c"] = s["w2c"].clone()
    # camera z = 1 - world z < 0 for every Gaussian: all of them sit behind every camera
    s["w2c"][:, :3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    means = s.pop("means").requires_grad_(True)
    out = rasterize(means, **s, background=BACKGROUND, backend=backend)
    assert_empty(out, 2, 29, 37)
    (out.features.sum() + out.alpha.sum()).backward()
    assert bool(torch.isfinite(means.grad).all())


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_scale_gives_background(backend, mode):
    s = scene32(n=20)
    s["scales"] = torch.zeros_like(s["scales"])
    assert_empty(rasterize(**s, background=BACKGROUND, backend=backend, mode=mode), 2, 29, 37)


@pytest.mark.parametrize("name", [*GAUSSIAN_INPUTS, "w2c", "K", "background"])
def test_nan_input_raises_naming_the_tensor(name):
    s = scene32(n=10)
    s["background"] = BACKGROUND.clone()
    s[name] = s[name].clone()
    s[name].view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=rf"\b{name}\b.*NaN"):
        rasterize(**s)


def test_bad_shapes_and_options_raise_clear_errors():
    s = scene32(n=10)
    with pytest.raises(ValueError, match=r"quats must have shape \(10, 4\)"):
        rasterize(**{**s, "quats": s["quats"][:, :3]})
    with pytest.raises(ValueError, match=r"K must have shape \(2, 3, 3\)"):
        rasterize(**{**s, "K": s["K"][:1]})
    with pytest.raises(ValueError, match="backend must be one of"):
        rasterize(**s, backend="vulkan")
    with pytest.raises(ValueError, match="mode must be one of"):
        rasterize(**s, mode="fancy")
    with pytest.raises(ValueError, match="scales must be non-negative"):
        rasterize(**{**s, "scales": -s["scales"]})


def test_auto_backend_selection():
    means32 = torch.zeros(1, 3)
    expected = "cpp" if rasterize_cpp.tile_kernel_available() else "torch"
    assert select_backend("auto", means32) == expected
    assert select_backend("auto", means32.double()) == "torch"
    assert select_backend("dense", means32) == "dense"


def test_missing_compiler_warns_and_falls_back(tmp_path, monkeypatch):
    monkeypatch.setenv("RELIGHTANYONE_CACHE", str(tmp_path))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert rasterize_cpp.load_tile_kernel.__wrapped__() is None
    assert any("using the slower PyTorch path" in str(w.message) for w in caught)
    assert str(tmp_path) in " ".join(str(w.message) for w in caught)


def test_build_cache_name_tracks_source_and_torch():
    name = rasterize_cpp.extension_name()
    assert name.startswith("relightanyone_raster_") and len(name) == len("relightanyone_raster_") + 16
    assert name == rasterize_cpp.extension_name()


def test_antialiased_zero_scale_gaussian_has_finite_gradients_on_the_torch_path():
    """The antialiasing compensation is sqrt(det ratio); at a zero-scale Gaussian the ratio is 0 and a
    plain sqrt would send an infinite slope (NaN) into every gradient."""
    generator = torch.Generator().manual_seed(0)
    count = 5
    means = torch.randn(count, 3, dtype=torch.float64, generator=generator) * 0.05
    means[:, 2] += 1.0
    quats = torch.randn(count, 4, dtype=torch.float64, generator=generator)
    scales = torch.full((count, 3), 0.02, dtype=torch.float64)
    scales[0] = 0.0
    opacities = torch.full((count,), 0.8, dtype=torch.float64)
    features = torch.rand(count, 3, dtype=torch.float64, generator=generator)
    inputs = (means, quats, scales, opacities, features)
    for tensor in inputs:
        tensor.requires_grad_(True)
    w2c = torch.eye(4, dtype=torch.float64)[None]
    K = torch.tensor([[[60.0, 0.0, 16.0], [0.0, 60.0, 16.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    image, _, _ = rasterize(*inputs, w2c, K, 32, 32, mode="antialiased", backend="torch")
    image.sum().backward()
    assert all(torch.isfinite(tensor.grad).all() for tensor in inputs)
    assert image.abs().sum() > 0
