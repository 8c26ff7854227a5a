"""The compiled CPU backend against gsplat's CUDA rasterizer, images and gradients (needs CUDA and the
``cuda`` extra)."""

from __future__ import annotations

import pytest
import torch
from helpers.raster_scenes import GAUSSIAN_INPUTS, assert_close, random_scene, render_with_grads

pytestmark = pytest.mark.gpu


def _gsplat_cuda_reason() -> str | None:
    if not torch.cuda.is_available():
        return "CUDA is not available on this machine"
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return "gsplat (the cuda extra) is not installed"
    return None


@pytest.mark.skipif(_gsplat_cuda_reason() is not None, reason=str(_gsplat_cuda_reason()))
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_compiled_cpu_backend_agrees_with_gsplat_cuda(mode):
    scene = random_scene(n=300, cameras=2, width=70, height=50, seed=13, channels=4)
    background = torch.tensor([0.1, 0.2, 0.3, 0.4])
    cpu_out, cpu_grads = render_with_grads(scene, "cpp", torch.float32, mode=mode, background=background)
    cuda_scene = {k: (v.cuda() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    gpu_out, gpu_grads = render_with_grads(
        cuda_scene, "gsplat", torch.float32, mode=mode, background=background.cuda()
    )
    assert float(cpu_out[1].max()) > 0.5
    for label, a, b in zip(("features", "alpha", "depth"), gpu_out, cpu_out, strict=True):
        assert_close(a.cpu(), b, 1e-4, label)
    for key in GAUSSIAN_INPUTS:
        assert_close(gpu_grads[key].cpu(), cpu_grads[key], 1e-4, f"d/d{key}")
