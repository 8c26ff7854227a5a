"""Environment maps: orientation, Voronoi-cell relighting weights, EXR input/output."""

from __future__ import annotations

import numpy as np
import pytest

from relightanyone.synth.envmap import (
    envmap_light_weights,
    latlong_directions,
    olat_relight_weights,
    procedural_envmaps,
    read_exr,
    write_exr,
)


def test_procedural_maps_are_deterministic_and_shaped():
    a = procedural_envmaps(3, seed=5)
    b = procedural_envmaps(3, seed=5)
    c = procedural_envmaps(3, seed=6)
    assert [name for name, _ in a] == ["env_000", "env_001", "env_002"]
    for (_, x), (_, y), (_, z) in zip(a, b, c, strict=True):
        assert x.shape == (10, 20, 3) and x.dtype == np.float32 and x.min() >= 0
        np.testing.assert_array_equal(x, y)
        assert not np.array_equal(x, z)


def test_map_orientation_front_is_plus_z_and_up_is_plus_y():
    dirs, omega = latlong_directions(10, 20)
    assert np.isclose(omega.sum(), 4 * np.pi)
    front = 0.5 * (dirs[5, 9, 0] + dirs[5, 10, 0])  # the two columns either side of u = 0.5
    assert front[2] > 0.95
    assert dirs[0, 0, 0, 1] > 0.95 and dirs[-1, 0, 0, 1] < -0.95  # top row looks up
    assert dirs[5, 15, 0, 0] > 0.95  # three quarters across looks toward +x


def test_voronoi_weights_integrate_the_map():
    env = np.zeros((10, 20, 3), np.float32)
    env[4:6, 9:11] = [1.0, 2.0, 3.0]  # a patch straight ahead (+z)
    lights = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0]])
    w = envmap_light_weights(env, lights)
    dirs, omega = latlong_directions(10, 20)
    total = (env * omega[..., 0:1]).sum(axis=(0, 1))
    np.testing.assert_allclose(w.sum(axis=0), total, rtol=1e-10)
    np.testing.assert_allclose(w[0], total, rtol=1e-10)  # the frontal light owns the whole patch
    assert np.all(w[1:] == 0)
    # Uniform white sky of radiance 1: each of 6 axis lights gets 4 pi / 6.
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    w_uniform = envmap_light_weights(np.ones((10, 20, 3), np.float32), axes, subsamples=16)
    np.testing.assert_allclose(w_uniform[:, 0], 4 * np.pi / 6, rtol=0.03)


def test_olat_weights_divide_by_the_light_irradiance():
    env = procedural_envmaps(1, seed=1)[0][1]
    positions = np.array([[0, 0, 2.0], [0, 2.0, 0], [2.0, 0, 0], [0, -2.0, 0], [-2.0, 0, 0], [0, 0, -2.0]])
    intensities = np.full((6, 3), 8.0)  # irradiance 8 / 2^2 = 2 at the head centre
    w = olat_relight_weights(env, positions, intensities)
    np.testing.assert_allclose(w, envmap_light_weights(env, positions / 2.0) / 2.0)
    with pytest.raises(ValueError, match="positive"):
        olat_relight_weights(env, positions, np.zeros((6, 3)))


def test_exr_round_trip_and_stable_bytes(tmp_path):
    image = np.random.default_rng(0).uniform(0, 50, size=(6, 9, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", image)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), image)
    write_exr(tmp_path / "b.exr", image)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    write_exr(tmp_path / "h.exr", image, half=True)
    np.testing.assert_allclose(read_exr(tmp_path / "h.exr"), image, rtol=1e-3)
    with pytest.raises(ValueError, match="a.exr"):
        write_exr(tmp_path / "a.exr", image[..., 0])
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        read_exr(tmp_path / "missing.exr")
