"""The ``relight`` and ``export`` commands on an avatar fitted in the sphere world (``helpers.sphere_world``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from helpers.sphere_world import LIGHTS, RIG_INTENSITY, SIZE, build_sphere_world, sphere_camera

from relightanyone.cli import cli
from relightanyone.model.fit.avatar import FittedAvatar
from relightanyone.model.fit.fitter import FitSettings, fit_subject
from relightanyone.render.camera import Cameras

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> tuple[dict[str, Path], Path, FittedAvatar]:
    """(world paths, avatar file, loaded avatar): s02 fitted with a few iterations."""
    world = build_sphere_world(tmp_path_factory.mktemp("avatar-world"))
    path = world["root"] / "s02.avatar"
    settings = FitSettings(inversion_iterations=3, finetune_iterations=1, views_per_step=2, progress=False)
    fit_subject(world["stage1"], world["stage2"], world["data"], "s02", settings=settings, out=path)
    return world, path, FittedAvatar.load(path)


def _run(command: str, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, [command, *(str(a) for a in args)])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


def _camera(c: int) -> Cameras:
    K, w2c = sphere_camera(c)
    return Cameras.create(K, w2c, SIZE, SIZE)


def _exr(path: Path) -> torch.Tensor:
    from relightanyone.render.envmap import load_envmap

    return load_envmap(path)


def test_export_re_renders_to_the_relit_avatar(fitted, tmp_path):
    from relightanyone.align.colour import linear_to_srgb
    from relightanyone.model.fit.ply import read_gaussian_ply
    from relightanyone.render.rasterize import rasterize

    _, path, avatar = fitted
    camera = _camera(1)
    centre = camera.centers[0].tolist()
    view = ",".join(repr(v) for v in centre)
    code, output = _run(
        "export",
        path,
        "--olat",
        2,
        "--view",
        view,
        "--colour-space",
        "linear",
        "--out",
        tmp_path / "a.ply",
    )
    assert code == 0, output
    splats = read_gaussian_ply(tmp_path / "a.ply")
    assert splats["means"].shape == (avatar.gaussian_count, 3)
    image = rasterize(
        splats["means"],
        splats["quats"],
        splats["scales"],
        splats["opacities"],
        splats["colours"],
        camera.w2c.float(),
        camera.K.float(),
        SIZE,
        SIZE,
    )[0]
    expected = avatar.relight(camera, avatar.olat(2))
    assert float(expected.amax()) > 0.01
    torch.testing.assert_close(image, expected, rtol=0, atol=2e-5)
    # Default: display-referred colours (sRGB of the clipped linear colour) for a frontal view.
    code, output = _run("export", path, "--olat", 2, "--view", view, "--out", tmp_path / "s.ply")
    assert code == 0, output
    srgb = read_gaussian_ply(tmp_path / "s.ply")["colours"]
    torch.testing.assert_close(srgb, linear_to_srgb(splats["colours"].clamp(0, 1)), rtol=0, atol=2e-6)
    code, output = _run("export", path, "--fitted-lighting", "--out", tmp_path / "f.ply")
    assert code == 0 and "view from" in output, output


def test_olat_and_point_light_at_the_rig_light_give_the_same_frames(fitted, tmp_path):
    _, path, avatar = fitted
    code, output = _run("relight", path, "--olat", 1, "--exr", "--no-progress", "--out", tmp_path / "olat")
    assert code == 0, output
    x, y, z = LIGHTS[1]
    explicit = f"{x},{y},{z},{RIG_INTENSITY},{RIG_INTENSITY},{RIG_INTENSITY}"
    for name, spec in (("explicit", explicit), ("default", f"{x},{y},{z}")):
        code, output = _run(
            "relight", path, "--point-light", spec, "--exr", "--no-progress", "--out", tmp_path / name
        )
        assert code == 0, output
    # Cameras of the fitted rows (the avatar's metadata), one frame each, equal to the avatar's own render.
    for c in range(4):
        olat = _exr(tmp_path / "olat" / f"cam{c:02d}_olat-001.exr")
        torch.testing.assert_close(olat, avatar.relight(_camera(c), avatar.olat(1))[0], rtol=0, atol=1e-6)
        for name in ("explicit", "default"):
            torch.testing.assert_close(
                _exr(tmp_path / name / f"cam{c:02d}_point.exr"), olat, rtol=0, atol=1e-6
            )
    assert float(olat.amax()) > 0.01
    assert (tmp_path / "olat" / "contact_sheet.png").is_file() and not list(
        (tmp_path / "olat").glob("strip*")
    )
    # A different light gives a different image: the comparison above can fail.
    code, _ = _run(
        "relight", path, "--point-light", "0,0,1", "--exr", "--no-progress", "--out", tmp_path / "other"
    )
    assert code == 0 and not torch.allclose(_exr(tmp_path / "other" / "cam00_point.exr"), olat, atol=1e-4)


def test_orbit_and_rotating_environment_write_frames_sheet_and_strips(fitted, tmp_path):
    from PIL import Image

    from relightanyone.align.colour import linear_to_srgb
    from relightanyone.render.envmap import latlong_directions, save_envmap

    _, path, _ = fitted
    code, output = _run(
        "relight",
        path,
        "--fitted-lighting",
        "--cameras",
        "orbit",
        "--count",
        4,
        "--size",
        20,
        "--exposure",
        -1,
        "--exr",
        "--no-progress",
        "--out",
        tmp_path / "orbit",
    )
    assert code == 0, output
    frames = sorted((tmp_path / "orbit").glob("orbit*_fitted.png"))
    assert [f.name for f in frames] == [f"orbit{i:03d}_fitted.png" for i in range(4)]
    with Image.open(tmp_path / "orbit" / "strip.webp") as strip:
        assert strip.n_frames == 4 and strip.size == (20, 20)
    # PNG = sRGB transfer of the linear frame after the exposure (half the light at -1 stop).
    png = np.asarray(Image.open(frames[0]), dtype=np.float64) / 255.0
    linear = _exr(tmp_path / "orbit" / "orbit000_fitted.exr")
    encoded = linear_to_srgb((linear * 0.5).clamp(0, 1)).permute(1, 2, 0).numpy()
    assert png.shape == (20, 20, 3) and float(linear.amax()) > 0.05
    np.testing.assert_allclose(png, encoded, atol=0.6 / 255)

    directions = latlong_directions(8, 16)
    env = 0.05 + 2.0 * (directions[..., 0].clamp(min=0) ** 2)[None].expand(3, -1, -1)  # light on the +x side
    save_envmap(tmp_path / "side.exr", env)
    code, output = _run(
        "relight",
        path,
        "--envmap",
        tmp_path / "side.exr",
        "--rotate",
        4,
        "--cameras",
        "orbit",
        "--count",
        2,
        "--size",
        16,
        "--strip-format",
        "gif",
        "--exposure",
        "auto",
        "--exr",
        "--no-progress",
        "--out",
        tmp_path / "env",
    )
    assert code == 0, output
    for camera in ("orbit000", "orbit001"):
        with Image.open(tmp_path / "env" / f"strip_{camera}.gif") as strip:
            assert strip.n_frames == 4
    first = _exr(tmp_path / "env" / "orbit000_side-rot000.exr")
    half_turn = _exr(tmp_path / "env" / "orbit000_side-rot002.exr")
    # Seen from the front, the light moves from the subject's left (+x, image right) to its right.
    assert float(first[:, :, 8:].sum()) > float(first[:, :, :8].sum())
    assert float(half_turn[:, :, :8].sum()) > float(half_turn[:, :, 8:].sum())
    # Auto exposure: one gain for all frames, the 99th percentile of lit pixels at 0.9 (sRGB 0.95).
    report = json.loads((tmp_path / "env" / "relight.json").read_text())
    assert report["exposure_stops"] is None and report["exposure_gain"] != 1.0
    brightest = max(int(np.asarray(Image.open(p)).max()) for p in (tmp_path / "env").glob("orbit*.png"))
    assert 235 <= brightest <= 255
    with Image.open(tmp_path / "env" / "contact_sheet.png") as sheet:
        assert sheet.size[0] == 4 * 16  # one column per rotation step


def test_cameras_from_another_dataset_subject(fitted, tmp_path):
    world, path, _ = fitted
    code, output = _run(
        "relight",
        path,
        "--olat",
        0,
        "--data",
        world["data"],
        "--subject",
        "s00",
        "--image-scale",
        0.5,
        "--no-progress",
        "--out",
        tmp_path / "data",
    )
    assert code == 0, output
    from PIL import Image

    frames = sorted((tmp_path / "data").glob("cam*_olat-000.png"))
    assert len(frames) == 4 and Image.open(frames[0]).size == (SIZE // 2, SIZE // 2)


def test_bad_inputs_give_clear_errors(fitted, tmp_path):
    world, path, _ = fitted
    out = ("--out", tmp_path / "bad")
    cases = [
        ((tmp_path / "missing.avatar", "--olat", 0), "no avatar file"),
        ((path, "--olat", 4), "rig has 4 lights, so K must be in 0..3"),
        ((path, "--olat", -1), "rig has 4 lights"),
        ((path,), "give exactly one lighting"),
        ((path, "--olat", 0, "--fitted-lighting"), "give exactly one lighting"),
        ((path, "--point-light", "1,2"), "expected 3 or 6"),
        ((path, "--envmap", tmp_path / "none.exr"), "none.exr: no such environment map"),
        ((path, "--olat", 0, "--rotate", 3), "--rotate turns an environment map"),
        ((path, "--olat", 0, "--data", world["data"]), "--data and --subject go together"),
        ((path, "--olat", 0, "--data", world["data"], "--subject", "zz"), "no subject 'zz'"),
        ((path, "--olat", 0, "--exposure", "bright"), "number of stops"),
        ((path, "--olat", 0, "--device", "toaster"), "'toaster' is not a torch device"),
    ]
    for args, message in cases:
        code, output = _run("relight", *args, "--no-progress", *out)
        assert code != 0 and message in " ".join(output.split()), (args, output)
    # An avatar whose metadata does not name its dataset (Fitter.avatar() without fit_subject's 'data').
    bare = FittedAvatar.load(path)
    bare.metadata.pop("data")
    bare.save(tmp_path / "bare.avatar")
    code, output = _run("relight", tmp_path / "bare.avatar", "--olat", 0, "--no-progress", *out)
    assert code != 0 and "pass --data DIR --subject S" in output, output
    code, output = _run("export", path, "--olat", 0, "--view", "1,2", "--out", tmp_path / "v.ply")
    assert code != 0 and "--view" in output, output
    assert not (tmp_path / "v.ply").exists()


def test_turning_a_prefiltered_map_equals_prefiltering_the_turned_map():
    import math

    from relightanyone.model.fit.avatar import prefilter_for_shading
    from relightanyone.model.fit.lighting_choice import rotate_prefiltered
    from relightanyone.render.envmap import rotate_envmap_yaw

    env = torch.rand(3, 8, 16, generator=torch.Generator().manual_seed(3))
    turned = rotate_prefiltered(prefilter_for_shading(env), math.pi / 2)
    expected = prefilter_for_shading(rotate_envmap_yaw(env, math.pi / 2))
    assert len(turned.levels) == len(expected.levels) > 1
    for level, reference in zip(turned.levels, expected.levels, strict=True):
        torch.testing.assert_close(level, reference, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(turned.levels[0], prefilter_for_shading(env).levels[0])


def test_frames_share_reflectance_and_splat_lightings_together_like_relight(fitted):
    from relightanyone.model.fit.avatar_tools import render_frames
    from relightanyone.model.fit.lighting_choice import NamedLighting

    _, _, avatar = fitted
    cameras = Cameras.cat([_camera(0), _camera(3)]).with_names(["a", "b"])
    lightings = [NamedLighting(f"l{k}", avatar.olat(k)) for k in range(3)]
    background = torch.tensor([0.1, 0.2, 0.3])
    frames = list(render_frames(avatar, cameras, lightings, background, progress=False, lightings_per_pass=2))
    assert [(c, label) for c, label, _ in frames] == [(c, f"l{k}") for c in "ab" for k in range(3)]
    for position, (_, _, image) in enumerate(frames):
        index, k = divmod(position, 3)
        expected = avatar.relight(cameras[index], avatar.olat(k), background)[0]
        torch.testing.assert_close(image, expected, rtol=0, atol=1e-6)


def test_a_folder_of_avatars_means_its_first_avatar(fitted, tmp_path):
    """What `relightanyone fit` writes is a folder; pipelines pass it without knowing subject names."""
    _, path, _ = fitted
    args = ["--olat", 0, "--cameras", "orbit", "--count", 1, "--size", 16, "--no-progress"]
    assert _run("relight", path, *args, "--out", tmp_path / "file")[0] == 0
    code, output = _run("relight", path.parent, *args, "--out", tmp_path / "folder")
    assert code == 0 and "s02.avatar" in output
    by_file = sorted(p.read_bytes() for p in (tmp_path / "file").glob("*.png"))
    assert by_file and by_file == sorted(p.read_bytes() for p in (tmp_path / "folder").glob("*.png"))
    empty = tmp_path / "empty"
    empty.mkdir()
    code, output = _run("relight", empty, *args, "--out", tmp_path / "none")
    assert code != 0 and "no *.avatar" in output
