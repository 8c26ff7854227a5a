"""Devices: every computing command takes ``--device``, and tensors are created on the device they are used on.

No GPU is needed: torch's ``meta`` device stands in for one. An operation mixing a ``meta`` tensor with a
CPU tensor fails just as one mixing CUDA and CPU tensors does, so a tensor created on the wrong device shows.
"""

from __future__ import annotations

import pytest
import torch
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.errors import InputError
from relightanyone.model.device import resolve_device
from relightanyone.model.fit.fitter import FitSettings, Fitter
from relightanyone.model.fit.views import FitViews
from relightanyone.model.train.losses import composite_over_background

# The commands that run torch models; each must take --device (default auto: CUDA when present).
COMPUTING_COMMANDS = (
    ("align-colour",),
    ("train", "stage1"),
    ("train", "stage2"),
    ("render", "stage1"),
    ("fit",),
    ("relight",),
    ("export",),
    ("expand",),
    ("evaluate",),
)


def _command(path: tuple[str, ...]):
    command = cli
    for name in path:
        command = command.commands[name]
    return command


@pytest.mark.parametrize("path", COMPUTING_COMMANDS, ids=" ".join)
def test_computing_commands_take_device_defaulting_to_auto(path):
    options = {p.name: p for p in _command(path).params}
    assert "device" in options, f"relightanyone {' '.join(path)} has no --device"
    assert options["device"].default == "auto"


def test_background_follows_the_render_device():
    # The single-stage trainer and the fitter draw backgrounds on the host and render on --device.
    render = torch.zeros(2, 3, 4, 4, device="meta")
    alpha = torch.zeros(2, 1, 4, 4, device="meta")
    background = torch.rand(2, 3)
    composited, target = composite_over_background(render, alpha, render, alpha, background)
    assert composited.device.type == "meta" and target.device.type == "meta"


def test_fit_views_and_step_backgrounds_on_the_fit_device():
    views = FitViews(
        images=torch.zeros(2, 3, 4, 4),
        masks=torch.zeros(2, 1, 4, 4),
        K=torch.eye(3).repeat(2, 1, 1),
        w2c=torch.eye(4).repeat(2, 1, 1),
        tracked_vertices=torch.zeros(5, 3),
        subject="s",
        frame=0,
        dataset="d",
        pattern="full",
    ).to("meta")
    assert {
        t.device.type for t in (views.images, views.masks, views.K, views.w2c, views.tracked_vertices)
    } == {"meta"}
    # The backgrounds of a step are drawn with NumPy (stateless) and must land beside the fitted code.
    fitter = Fitter.__new__(Fitter)
    fitter.settings = FitSettings()
    fitter.z_id = torch.nn.Parameter(torch.zeros(1, 4, device="meta"))
    assert fitter.step_backgrounds(3, 2).device.type == "meta"


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InputError, match="not a torch device"):
        resolve_device("gpu0")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_requested_without_cuda_is_one_line_error(tmp_path):
    (tmp_path / "data").mkdir()
    result = CliRunner().invoke(
        cli,
        ["train", "stage2", "--data", str(tmp_path / "data"), "--single-stage", "--out", str(tmp_path / "o")]
        + ["--device", "cuda"],
    )
    assert result.exit_code == 1, result.output
    assert "CUDA is not available" in result.output and "Traceback" not in result.output
