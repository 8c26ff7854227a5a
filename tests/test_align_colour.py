"""Colour maths: transfer functions, CCM application and fitting, dataset calibration files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from relightanyone.align.colour import (
    apply_ccm,
    apply_display_affine,
    apply_faceolat_colour_matrix,
    apply_nersemble_v2_colour,
    ccm_error,
    colour_matrix_problem,
    fit_affine_colour,
    fit_ccm,
    gamma_to_linear,
    linear_to_display,
    linear_to_gamma,
    linear_to_srgb,
    read_faceolat_colour_matrix,
    read_nersemble_colour_calibration,
    read_nersemble_v1_affine,
    srgb_to_linear,
)
from relightanyone.format.colour_alignment import read_learned_colour, write_learned_colour_matrix
from relightanyone.format.schema import COLOUR_ALIGNMENT_NAME

CAST = np.array([[0.92, 0.11, 0.02], [0.04, 0.81, 0.09], [0.01, 0.14, 1.12]])


# --- transfer functions ------------------------------------------------------------------------------


def test_srgb_known_values_numpy_and_torch():
    # IEC 61966-2-1: 0.5 encoded -> 0.21404 linear; 0.18 linear -> 0.46136 encoded; linear toe below 0.04045.
    assert srgb_to_linear(0.5) == pytest.approx(0.214041140, abs=1e-8)
    assert linear_to_srgb(0.18) == pytest.approx(0.461356129, abs=1e-8)
    assert srgb_to_linear(0.02) == pytest.approx(0.02 / 12.92, abs=1e-10)
    values = torch.tensor([[0.0, 0.02, 0.5, 1.0], [0.3, 0.7, 0.9, 0.1]], dtype=torch.float64)
    assert srgb_to_linear(values).numpy() == pytest.approx(srgb_to_linear(values.numpy()), abs=1e-9)
    roundtrip = linear_to_srgb(srgb_to_linear(values))
    assert roundtrip.shape == values.shape and torch.allclose(roundtrip, values, atol=1e-7)


def test_display_codes_known_values_numpy_and_torch():
    # 0.18 linear -> 0.461356 sRGB -> 117.65 -> 118; 0.5 -> 0.735357 -> 187.52 -> 188; clipped below 0 and above 1.
    linear = np.array([[0.18, 0.5, 1.0], [-0.2, 3.0, 0.0]])
    expected = np.array([[118, 188, 255], [0, 255, 0]], dtype=np.uint8)
    assert np.array_equal(linear_to_display(linear), expected)
    assert np.array_equal(linear_to_display(linear / 2, exposure=2.0), expected)
    codes = linear_to_display(torch.tensor(linear, dtype=torch.float32))
    assert codes.dtype == np.uint8 and np.array_equal(codes, expected)  # axes are kept


def test_gamma_22_matches_the_faceolat_encoding():
    assert gamma_to_linear(0.5) == pytest.approx(0.5**2.2)
    assert linear_to_gamma(0.2176376) == pytest.approx(0.5, abs=1e-6)
    assert gamma_to_linear(-0.1) == 0.0
    t = torch.tensor([0.25, 0.5])
    assert torch.allclose(linear_to_gamma(gamma_to_linear(t)), t)


# --- applying matrices ---------------------------------------------------------------------------------


def test_apply_ccm_numpy_channels_last_equals_torch_channels_first():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (5, 7, 3)).astype(np.float32)
    offset = np.array([0.01, -0.02, 0.03])
    out = apply_ccm(image, CAST, offset)
    assert out.dtype == np.float32 and out.shape == image.shape
    assert out[2, 3] == pytest.approx(CAST @ image[2, 3] + offset, abs=1e-6)
    batch = torch.from_numpy(image).permute(2, 0, 1)[None].requires_grad_(True)
    out_t = apply_ccm(batch, CAST, offset)
    assert out_t.shape == (1, 3, 5, 7)
    assert out_t[0].permute(1, 2, 0).detach().numpy() == pytest.approx(out, abs=1e-6)
    out_t.sum().backward()  # differentiable for the learned matrix
    assert batch.grad is not None


def test_apply_ccm_passes_gradients_to_a_torch_matrix():
    learned = torch.eye(3, dtype=torch.float64, requires_grad=True)
    image = torch.rand(2, 3, 4, 4, dtype=torch.float64)
    apply_ccm(image, learned).sum().backward()
    # d(sum of M @ rgb)/dM[i, j] = sum over pixels of rgb_j
    expected = image.sum(dim=(0, 2, 3)).expand(3, 3)
    assert torch.allclose(learned.grad, expected)
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        apply_ccm(image, torch.eye(4))


def test_apply_ccm_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="3 channels"):
        apply_ccm(np.zeros((4, 4, 4)), np.eye(3))
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        apply_ccm(np.zeros((4, 4, 3)), np.eye(4))
    with pytest.raises(ValueError, match="NaN"):
        apply_ccm(np.zeros((4, 4, 3)), np.full((3, 3), np.nan))


def test_faceolat_recipe_subtracts_black_then_multiplies_then_clips():
    M = np.array([[1.45, -0.04, 0.1], [-0.03, 1.32, 0.09], [-0.05, 0.02, 1.55]])
    black = np.array([0.0009, 0.0009, 0.0008])
    rgb = np.array([[0.2, 0.1, 0.05], [0.0, 0.0005, 0.0]])
    out = apply_faceolat_colour_matrix(rgb, M, black)
    assert out[0] == pytest.approx(M @ (rgb[0] - black))
    assert np.all(out[1] >= 0) and out[1][0] == 0.0  # M @ (rgb - black) is negative there, clipped


def test_nersemble_v1_display_affine_uses_row_vectors_and_clips():
    A = np.array([[1.1, 0.05, 0.0, 0.01], [0.0, 0.9, 0.02, -0.02], [0.03, 0.0, 1.05, 0.0]])
    rgb = np.array([0.5, 0.25, 0.75])
    # rgb @ A[:3, :3] + A[:3, 3] (the v1 loaders' formula)
    expected = rgb @ A[:3, :3] + A[:3, 3]
    assert apply_display_affine(rgb, A) == pytest.approx(expected)
    assert apply_display_affine(np.array([1.0, 1.0, 1.0]), A).max() == 1.0


def test_read_nersemble_v1_affine(tmp_path):
    path = tmp_path / "222200037.npy"
    np.save(path, np.eye(4))
    assert read_nersemble_v1_affine(path) == pytest.approx(np.eye(4)[:3])
    np.save(path, np.eye(3))
    with pytest.raises(ValueError, match="222200037.npy"):
        read_nersemble_v1_affine(path)


def test_nersemble_v2_calibration_reads_3x3_and_affine_ccms(tmp_path):
    data = {"222200037": CAST.tolist(), "222200036": np.hstack([CAST, [[0.01], [0.0], [-0.01]]]).tolist()}
    path = tmp_path / "color_calibration.json"
    path.write_text(json.dumps(data))
    calib = read_nersemble_colour_calibration(path)
    assert list(calib) == ["222200036", "222200037"]
    M, offset = calib["222200037"]
    assert M == pytest.approx(CAST) and offset == pytest.approx(np.zeros(3))
    assert calib["222200036"][1] == pytest.approx([0.01, 0.0, -0.01])
    # v2 recipe: decode sRGB, apply CCM in linear light.
    pixel = np.array([0.5, 0.5, 0.5])
    assert apply_nersemble_v2_colour(pixel, M, offset) == pytest.approx(
        CAST @ np.full(3, 0.214041140), abs=1e-8
    )


def test_nersemble_v2_calibration_errors_name_file_and_camera(tmp_path):
    path = tmp_path / "color_calibration.json"
    path.write_text(json.dumps({"222200037": np.zeros((3, 10)).tolist()}))
    with pytest.raises(ValueError, match=r"color_calibration.json.*222200037.*\(3, 10\)"):
        read_nersemble_colour_calibration(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="color_calibration.json"):
        read_nersemble_colour_calibration(path)
    with pytest.raises(ValueError, match="NaN"):
        read_nersemble_colour_calibration({"1": [[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]})


SINGULAR = {
    "all zero": np.zeros((3, 3)),
    "rank 2": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.0]]),
    "rank 1": np.outer([1.0, 0.9, 0.8], [0.3, 0.3, 0.4]),
}


def test_only_an_invertible_colour_matrix_passes():
    assert colour_matrix_problem(CAST) is None and colour_matrix_problem(1e-3 * CAST) is None
    for name, matrix in SINGULAR.items():
        assert "singular" in colour_matrix_problem(matrix), name
    assert "NaN" in colour_matrix_problem(np.full((3, 3), np.nan))


@pytest.mark.parametrize("name", sorted(SINGULAR))
def test_every_colour_file_reader_refuses_a_singular_matrix_naming_the_file(tmp_path, name):
    matrix = SINGULAR[name]
    v2 = tmp_path / "color_calibration.json"
    v2.write_text(json.dumps({"222200037": CAST.tolist(), "222200038": matrix.tolist()}))
    with pytest.raises(ValueError, match=r"color_calibration\.json: CCM of camera 222200038: .*singular"):
        read_nersemble_colour_calibration(v2)
    v1 = tmp_path / "222200037.npy"
    np.save(v1, np.hstack([matrix.T, np.zeros((3, 1))]))
    with pytest.raises(ValueError, match=r"222200037\.npy: .*singular"):
        read_nersemble_v1_affine(v1)
    faceolat = tmp_path / "colorcalib_exr.mat"
    np.savetxt(faceolat, np.vstack([np.hstack([matrix, np.zeros((3, 1))]), [0, 0, 0, 1]]))
    with pytest.raises(ValueError, match=r"colorcalib_exr\.mat: .*singular"):
        read_faceolat_colour_matrix(faceolat)
    learned = tmp_path / COLOUR_ALIGNMENT_NAME
    learned.write_text(
        json.dumps({"format": "relightanyone.colour_alignment", "version": 1, "matrix": matrix.tolist()})
    )
    with pytest.raises(ValueError, match=r"colour_alignment\.json: field 'matrix': .*singular"):
        read_learned_colour(tmp_path)


# --- FaceOLAT real files ---------------------------------------------------------------------------------


def test_faceolat_real_exr_matrix(real_fixtures):
    M, black = read_faceolat_colour_matrix(real_fixtures / "faceolat" / "colorcalib_exr.mat")
    assert M[0] == pytest.approx([1.38336957, -0.0137942024, 0.0225721952])
    assert M[2, 2] == pytest.approx(1.75287747)
    assert black == pytest.approx(np.zeros(3))


def test_faceolat_real_relighting_matrix_has_a_black_level(real_fixtures):
    M, black = read_faceolat_colour_matrix(real_fixtures / "faceolat" / "colorcalib.mat")
    assert np.diag(M) == pytest.approx([1.45, 1.32, 1.55])
    assert black == pytest.approx([0.0009, 0.0009, 0.0008])


@pytest.mark.parametrize(
    "text, problem",
    [
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "4×4"),
        ("1 0 0 0\n0 nan 0 0\n0 0 1 0\n0 0 0 1", "NaN"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n1 0 0 1", "last row"),
        ("1 0 0 0\n0 1 0 0\n0 0 x 0\n0 0 0 1", "numeric"),
        ("1 0 0 0\n2 0 0 0\n0 0 1 0\n0 0 0 1", "singular"),
    ],
)
def test_malformed_faceolat_matrix_errors_name_the_file(tmp_path, text, problem):
    path = tmp_path / "broken_colorcalib.mat"
    path.write_text(text)
    with pytest.raises(ValueError, match=problem) as info:
        read_faceolat_colour_matrix(path)
    assert "broken_colorcalib.mat" in str(info.value)


def test_missing_faceolat_matrix_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.mat"):
        read_faceolat_colour_matrix(tmp_path / "nothing.mat")


# --- fitting --------------------------------------------------------------------------------------------


def test_fit_ccm_recovers_an_inverse_cast_with_both_methods():
    rng = np.random.default_rng(1)
    reference = rng.uniform(0.02, 0.9, (24, 3))
    measured = reference @ np.linalg.inv(CAST).T * 0.7  # a cast and an exposure
    for method in ("Cheung 2004", "Finlayson 2015"):
        M = fit_ccm(measured, reference, method=method)
        assert M @ np.linalg.inv(CAST) * 0.7 == pytest.approx(np.eye(3), abs=1e-9)
        err = ccm_error(measured, reference, M)
        assert err.rmse < 1e-9 and err.delta_e_max < 1e-6
    with pytest.raises(ValueError, match="unknown CCM method"):
        fit_ccm(measured, reference, method="Vandermonde")


def test_fit_affine_colour_recovers_offset():
    rng = np.random.default_rng(2)
    measured = rng.uniform(0, 1, (30, 3))
    reference = measured @ CAST.T + [0.02, -0.01, 0.03]
    M, offset = fit_affine_colour(measured, reference)
    assert M == pytest.approx(CAST, abs=1e-9) and offset == pytest.approx([0.02, -0.01, 0.03], abs=1e-9)


def test_ccm_error_reports_a_known_delta_e():
    grey = np.full((3, 3), 0.18)
    err = ccm_error(grey, grey, np.eye(3) * 1.0)
    assert err.delta_e_mean == pytest.approx(0.0, abs=1e-9)
    # Doubling linear mid-grey: L* goes 49.50 -> 66.52; ΔE2000 = 17.03 / S_L(58.0) = 17.03 / 1.105 = 15.41
    err = ccm_error(grey, grey, np.eye(3) * 2.0)
    assert err.delta_e_mean == pytest.approx(15.41, abs=0.02)
    assert err.rmse == pytest.approx(0.18)


# --- learned matrix storage ---------------------------------------------------------------------------------


def test_learned_matrix_roundtrip_and_absence(tmp_path):
    assert read_learned_colour(tmp_path) is None
    path = write_learned_colour_matrix(tmp_path, CAST, {"reference_dataset": "faceolat", "step": 1200})
    assert path.name == COLOUR_ALIGNMENT_NAME
    learned = read_learned_colour(tmp_path)
    assert learned.matrix == pytest.approx(CAST, abs=0) and learned.for_camera("any") is learned.matrix
    first = path.read_bytes()
    write_learned_colour_matrix(tmp_path, CAST, {"step": 1200, "reference_dataset": "faceolat"})
    assert path.read_bytes() == first  # deterministic bytes
    document = json.loads(first)
    assert document["info"]["reference_dataset"] == "faceolat" and document["version"] == 2
    # Per-camera matrices: a listed camera uses its own, the others the dataset's.
    own = np.diag([1.2, 1.0, 0.8])
    write_learned_colour_matrix(tmp_path, CAST, cameras={"400137": own})
    learned = read_learned_colour(tmp_path)
    assert learned.for_camera("400137") == pytest.approx(own, abs=0)
    assert learned.for_camera("400163") == pytest.approx(CAST, abs=0)
    # A version-1 document (no per-camera matrices) is still read.
    path.write_text(
        json.dumps({"format": "relightanyone.colour_alignment", "version": 1, "matrix": CAST.tolist()})
    )
    assert read_learned_colour(tmp_path).cameras == {}


def test_learned_matrix_malformed_file_names_the_file(tmp_path):
    path = tmp_path / COLOUR_ALIGNMENT_NAME
    path.write_text(
        json.dumps({"format": "relightanyone.colour_alignment", "version": 1, "matrix": [[1, 0]]})
    )
    with pytest.raises(ValueError, match="colour_alignment.json.*matrix"):
        read_learned_colour(tmp_path)
    path.write_text("[")
    with pytest.raises(ValueError, match="colour_alignment.json"):
        read_learned_colour(tmp_path)
    singular = {"format": "relightanyone.colour_alignment", "version": 2, "matrix": CAST.tolist()}
    path.write_text(json.dumps({**singular, "cameras": {"cam03": np.zeros((3, 3)).tolist()}}))
    with pytest.raises(ValueError, match=r"colour_alignment\.json: field 'cameras\.cam03': .*singular"):
        read_learned_colour(tmp_path)
    path.write_text(json.dumps({**singular, "cameras": [1, 2]}))
    with pytest.raises(ValueError, match="colour_alignment.json: field 'cameras'"):
        read_learned_colour(tmp_path)
    with pytest.raises(ValueError, match="finite"):
        write_learned_colour_matrix(tmp_path, CAST, {"bad": float("nan")})
