"""Colour maths: transfer functions, colour-correction matrices, dataset calibration files.

Conventions (see ``docs/align.md``):

* Colour matrices act on **column vectors** of scene-linear RGB: ``out = M @ (rgb - black_level) + offset``.
* Images are channel-last ``(..., 3)`` (numpy-style ``H×W×3``) or channel-first ``B×3×H×W`` (torch-style);
  an array with 4 dimensions is read as ``B×3×H×W``, anything else as ``(..., 3)``. Both numpy arrays and
  torch tensors are accepted and the same type comes back (torch stays differentiable).
* Nothing is clipped unless a function says so: dataset recipes that clip (FaceOLAT clips at 0, NeRSemble v1
  clips to [0, 1] in display space) do it in their own helpers.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from relightanyone.render.errors import FileFormatError

with warnings.catch_warnings():
    # colour-science warns once that matplotlib (plotting only) is missing.
    warnings.simplefilter("ignore")
    import colour

COLOUR_ALIGNMENT_FORMAT = "relightanyone.colour_alignment"
COLOUR_ALIGNMENT_VERSION = 2  # 2 adds per-camera matrices; version 1 documents are still read
READABLE_COLOUR_ALIGNMENT_VERSIONS = (1, 2)

FACEOLAT_DISPLAY_GAMMA = 2.2

CCM_METHODS = ("Cheung 2004", "Finlayson 2015")
# A colour matrix must keep all three colour directions: its smallest singular value at least this
# fraction of its largest. An all-zero or rank-deficient matrix maps some colours to black (or noise
# amplified a million times), so it is refused wherever a matrix enters.
MIN_COLOUR_MATRIX_SINGULAR_RATIO = 1e-6


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _channel_dim(image: Any, channel_dim: int | None) -> int:
    """Channel axis of ``image``: 1 for 4-D ``B×3×H×W``, else the last axis (validated to have size 3)."""
    ndim = image.ndim
    dim = channel_dim if channel_dim is not None else (1 if ndim == 4 else -1)
    if ndim == 0 or image.shape[dim] != 3:
        raise ValueError(
            f"expected an RGB image with 3 channels on axis {dim} ((..., 3) or (B, 3, H, W)); "
            f"got shape {tuple(image.shape)}"
        )
    return dim


def _as_matrix(M: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    if _is_torch(M):
        M = M.detach().cpu().numpy()
    arr = np.asarray(M, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def colour_matrix_problem(M: Any) -> str | None:
    """Why ``M (3, 3)`` cannot be a colour matrix (not 3×3, not finite, singular), or None when it can."""
    arr = np.asarray(M, dtype=np.float64)
    if arr.shape != (3, 3):
        return f"the colour matrix must be 3×3, got shape {arr.shape}"
    if not np.all(np.isfinite(arr)):
        return "the colour matrix contains NaN or infinite values"
    singular = np.linalg.svd(arr, compute_uv=False)
    if not singular[0] > 0 or singular[-1] < MIN_COLOUR_MATRIX_SINGULAR_RATIO * singular[0]:
        return (
            f"the colour matrix is singular (singular values {np.round(singular, 9).tolist()}): it maps some "
            "colours to black"
        )
    return None


def check_colour_matrix(M: Any, where: str) -> np.ndarray:
    """``M`` as a ``(3, 3)`` float64 colour matrix; ``ValueError`` naming ``where`` and the problem otherwise
    (see :func:`colour_matrix_problem`)."""
    problem = colour_matrix_problem(M)
    if problem is not None:
        raise FileFormatError(f"{where}: {problem}")
    return np.asarray(M, dtype=np.float64).copy()


def _as_tensor(value: Any, shape: tuple[int, ...], name: str, like: Any) -> Any:
    """``value`` as a tensor on ``like``'s device and dtype; tensors are kept (and stay differentiable)."""
    import torch

    if not _is_torch(value):
        value = _as_matrix(value, shape, name)
    tensor = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if tuple(tensor.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(tensor.shape)}")
    return tensor


# ---------------------------------------------------------------------------------------------------------
# Transfer functions
# ---------------------------------------------------------------------------------------------------------


def _elementwise_kornia(x: Any, fn: Any) -> Any:
    """Apply a kornia ``(*, 3, H, W)`` colour function elementwise to a tensor of any shape."""
    import torch.nn.functional as F

    n = x.numel()
    flat = F.pad(x.reshape(-1), (0, (-n) % 3))
    return fn(flat.reshape(1, 3, -1, 1)).reshape(-1)[:n].reshape(x.shape)


def srgb_to_linear(x: Any) -> Any:
    """Decode sRGB-encoded values (IEC 61966-2-1 piecewise EOTF) to linear light.

    Args:
        x: array or tensor of any shape, nominally in [0, 1].
    Returns:
        Same shape and type. numpy uses ``colour.cctf_decoding(x, "sRGB")``; torch uses
        ``kornia.color.rgb_to_linear_rgb`` (differentiable).
    """
    if _is_torch(x):
        import kornia

        return _elementwise_kornia(x, kornia.color.rgb_to_linear_rgb)
    return colour.cctf_decoding(np.asarray(x, dtype=np.float64), function="sRGB")


def linear_to_srgb(x: Any) -> Any:
    """Encode linear light with the sRGB inverse EOTF; inverse of :func:`srgb_to_linear`. Any shape."""
    if _is_torch(x):
        import kornia

        return _elementwise_kornia(x, kornia.color.linear_rgb_to_rgb)
    return colour.cctf_encoding(np.asarray(x, dtype=np.float64), function="sRGB")


def linear_to_display(image: Any, exposure: float = 1.0) -> np.ndarray:
    """Scene-linear RGB -> sRGB-encoded uint8 for pictures: ``round(255 · srgb(clip(image · exposure, 0, 1)))``.

    Any shape; the axes are kept (a (3, H, W) tensor gives (3, H, W) codes). The transfer function is
    :func:`linear_to_srgb`, evaluated like it in the input's type: float64 for numpy, the tensor's dtype for
    torch. Halves round up.
    """
    if _is_torch(image):
        encoded = linear_to_srgb((image.detach() * exposure).clamp(0.0, 1.0)).clamp(0.0, 1.0).cpu().numpy()
    else:
        encoded = np.clip(linear_to_srgb(np.clip(np.asarray(image) * exposure, 0.0, 1.0)), 0.0, 1.0)
    return (encoded * 255.0 + 0.5).astype(np.uint8)


def gamma_to_linear(x: Any, gamma: float = FACEOLAT_DISPLAY_GAMMA) -> Any:
    """Decode a pure power-law encoding: ``max(x, 0) ** gamma``.

    FaceOLAT AVIFs were written as ``clip(rgb_linear, 0) ** (1/2.2)`` (not the sRGB curve), so they decode
    with the default ``gamma=2.2``. Any shape; numpy or torch.
    """
    if _is_torch(x):
        return x.clamp(min=0) ** gamma
    return np.maximum(np.asarray(x, dtype=np.float64), 0.0) ** gamma


def linear_to_gamma(x: Any, gamma: float = FACEOLAT_DISPLAY_GAMMA) -> Any:
    """Encode linear light with a pure power law ``max(x, 0) ** (1 / gamma)``. Any shape; numpy or torch."""
    if _is_torch(x):
        return x.clamp(min=0) ** (1.0 / gamma)
    return np.maximum(np.asarray(x, dtype=np.float64), 0.0) ** (1.0 / gamma)


# ---------------------------------------------------------------------------------------------------------
# Applying colour matrices
# ---------------------------------------------------------------------------------------------------------


def apply_ccm(
    image: Any,
    M: Any,
    offset: Any = None,
    *,
    black_level: Any = None,
    clip_at_zero: bool = False,
    channel_dim: int | None = None,
) -> Any:
    """Apply a 3×3 colour matrix to linear RGB: ``out = M @ (rgb - black_level) + offset`` per pixel.

    Args:
        image: ``(..., 3)`` or ``(B, 3, H, W)`` numpy array or torch tensor, scene-linear.
        M: ``(3, 3)`` matrix acting on column vectors.
        offset: ``(3,)`` added after the matrix, or None.
        black_level: ``(3,)`` subtracted before the matrix, or None (FaceOLAT's 4th column).
        clip_at_zero: clamp the result at 0 (FaceOLAT's recipe does; a plain CCM does not).
        channel_dim: override the channel axis (default: 1 for 4-D input, else -1).
    Returns:
        Same shape and container type as ``image``; float (torch keeps its dtype, numpy becomes float64
        unless the input was float32).
    """
    dim = _channel_dim(image, channel_dim)
    if _is_torch(image):
        # Torch parameters stay tensors, so a learned matrix receives gradients.
        M = _as_tensor(M, (3, 3), "colour matrix M", image)
        offset = None if offset is None else _as_tensor(offset, (3,), "colour offset", image)
        black_level = None if black_level is None else _as_tensor(black_level, (3,), "black level", image)
        x = image.movedim(dim, -1)
        if black_level is not None:
            x = x - black_level
        x = x @ M.T
        if offset is not None:
            x = x + offset
        if clip_at_zero:
            x = x.clamp(min=0)
        return x.movedim(-1, dim)
    M = _as_matrix(M, (3, 3), "colour matrix M")
    offset = None if offset is None else _as_matrix(offset, (3,), "colour offset")
    black_level = None if black_level is None else _as_matrix(black_level, (3,), "black level")
    arr = np.asarray(image)
    work_dtype = np.float32 if arr.dtype == np.float32 else np.float64
    x = np.moveaxis(arr.astype(work_dtype, copy=False), dim, -1)
    if black_level is not None:
        x = x - black_level.astype(work_dtype)
    x = x @ M.T.astype(work_dtype)
    if offset is not None:
        x = x + offset.astype(work_dtype)
    if clip_at_zero:
        x = np.maximum(x, 0)
    return np.moveaxis(x, -1, dim)


def apply_faceolat_colour_matrix(image_linear: Any, M: Any, black: Any, **kwargs: Any) -> Any:
    """FaceOLAT ``exr2avif.py`` recipe on linear EXR RGB: ``max(M @ (rgb - black), 0)``.

    Args: image_linear ``(..., 3)`` or ``(B, 3, H, W)``; ``M (3, 3)`` and ``black (3,)`` from
    :func:`read_faceolat_colour_matrix`. Returns the same shape.
    """
    return apply_ccm(image_linear, M, black_level=black, clip_at_zero=True, **kwargs)


def apply_display_affine(image_display: Any, A: Any, **kwargs: Any) -> Any:
    """NeRSemble v1 per-camera colour correction, applied in display (sRGB-encoded) space.

    The v1 loaders compute ``clip(rgb01 @ A[:3, :3] + A[:3, 3], 0, 1)`` on the PNG values without any
    linearisation, i.e. row vectors times ``A[:3, :3]``. Decode the result with :func:`srgb_to_linear`
    afterwards to get scene-linear colour.

    Args:
        image_display: ``(..., 3)`` or ``(B, 3, H, W)`` in [0, 1], sRGB-encoded.
        A: ``(>=3, 4)`` affine from ``annotations/{SEQ}/color_correction/{serial}.npy``.
    Returns:
        Same shape, display-encoded, clipped to [0, 1].
    """
    A = np.asarray(A, dtype=np.float64)
    if A.ndim != 2 or A.shape[0] < 3 or A.shape[1] < 4:
        raise ValueError(f"NeRSemble v1 colour affine must be at least 3×4, got shape {A.shape}")
    # Row-vector convention (rgb @ A) equals column-vector convention with the transpose.
    out = apply_ccm(image_display, A[:3, :3].T, A[:3, 3], **kwargs)
    return out.clamp(0, 1) if _is_torch(out) else np.clip(out, 0, 1)


def read_nersemble_v1_affine(path: str | os.PathLike) -> np.ndarray:
    """Read a NeRSemble v1 ``color_correction/{serial}.npy`` affine. Returns ``(3, 4)`` float64."""
    path = Path(path)
    try:
        A = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"{path}: cannot read NeRSemble colour affine ({exc})") from exc
    A = np.asarray(A, dtype=np.float64)
    if A.ndim != 2 or A.shape[0] < 3 or A.shape[1] < 4:
        raise FileFormatError(f"{path}: NeRSemble colour affine must be at least 3×4, got shape {A.shape}")
    if not np.all(np.isfinite(A[:3, :4])):
        raise FileFormatError(f"{path}: NeRSemble colour affine contains NaN or infinite values")
    check_colour_matrix(A[:3, :3], str(path))
    return A[:3, :4].copy()


# ---------------------------------------------------------------------------------------------------------
# Dataset calibration files
# ---------------------------------------------------------------------------------------------------------


def read_faceolat_colour_matrix(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a FaceOLAT ``colorcalib_exr.mat`` / ``colorcalib.mat`` (plain text 4×4, not MATLAB binary).

    Layout: rows 0-2 are ``[M | black]``, row 3 is ``0 0 0 1``. FaceOLAT applies it to linear RGB as
    ``max(M @ (rgb - black), 0)`` (column vectors; the 4th column is a black level *subtracted before* the
    matrix, not an offset added after). See :func:`apply_faceolat_colour_matrix`.

    Returns:
        ``(M (3, 3), black (3,))`` float64.
    Raises:
        FileNotFoundError / ValueError naming the file and the problem.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: FaceOLAT colour matrix file not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns on empty files; we report below
            values = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise FileFormatError(f"{path}: not a whitespace-separated numeric 4×4 matrix ({exc})") from exc
    if values.shape != (4, 4):
        raise FileFormatError(f"{path}: expected a 4×4 colour matrix, got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise FileFormatError(f"{path}: colour matrix contains NaN or infinite values")
    if not np.allclose(values[3], [0.0, 0.0, 0.0, 1.0]):
        raise FileFormatError(
            f"{path}: last row of the colour matrix must be '0 0 0 1', got {values[3].tolist()}"
        )
    return check_colour_matrix(values[:3, :3], str(path)), values[:3, 3].copy()


def read_nersemble_colour_calibration(
    path_or_dict: str | os.PathLike | Mapping[str, Any],
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read NeRSemble v2 ``calibration/color_calibration.json``: ``{serial: CCM}``.

    NeRSemble applies each CCM with Cheung-2004 augmentation in **linear light** (after sRGB decoding).
    With 3 terms the augmentation is ``[R, G, B]`` (offset 0); with 4 terms ``[R, G, B, 1]`` (the 4th column is
    an offset added after the matrix). Higher-order polynomial CCMs have no 3×3 form and are refused.

    Returns:
        ``{serial (str): (M (3, 3), offset (3,))}`` float64, sorted by serial.
    """
    source = str(path_or_dict) if not isinstance(path_or_dict, Mapping) else "colour calibration dict"
    if isinstance(path_or_dict, Mapping):
        data = path_or_dict
    else:
        path = Path(path_or_dict)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: NeRSemble color_calibration.json not found")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise FileFormatError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, Mapping) or not data:
        raise FileFormatError(f"{source}: expected a non-empty JSON object mapping camera serial -> CCM")
    result: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for serial in sorted(data, key=str):
        try:
            ccm = np.asarray(data[serial], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise FileFormatError(
                f"{source}: CCM of camera {serial} is not a numeric matrix ({exc})"
            ) from exc
        if ccm.shape not in ((3, 3), (3, 4)):
            raise FileFormatError(
                f"{source}: CCM of camera {serial} has shape {ccm.shape}; only 3×3 and 3×4 (affine) "
                "Cheung-2004 matrices have a linear form"
            )
        if not np.all(np.isfinite(ccm)):
            raise FileFormatError(f"{source}: CCM of camera {serial} contains NaN or infinite values")
        offset = ccm[:, 3].copy() if ccm.shape[1] == 4 else np.zeros(3)
        result[str(serial)] = (check_colour_matrix(ccm[:, :3], f"{source}: CCM of camera {serial}"), offset)
    return result


def apply_nersemble_v2_colour(image_srgb: Any, M: Any, offset: Any, **kwargs: Any) -> Any:
    """NeRSemble v2 decode: sRGB-encoded frame ``(..., 3)`` / ``(B, 3, H, W)`` in [0, 1] → scene-linear.

    ``max(M @ srgb_to_linear(rgb) + offset, 0)``; the clip enforces the toolkit's [0, ∞) colour range.
    """
    out = apply_ccm(srgb_to_linear(image_srgb), M, offset, **kwargs)
    return out.clamp(min=0) if _is_torch(out) else np.maximum(out, 0)


# ---------------------------------------------------------------------------------------------------------
# Fitting and scoring
# ---------------------------------------------------------------------------------------------------------


def _as_colours(x: Any, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 3:
        raise ValueError(f"{name} must be (N, 3) with N >= 3, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def fit_ccm(measured: Any, reference: Any, method: str = "Cheung 2004") -> np.ndarray:
    """Least-squares 3×3 colour matrix with ``reference ≈ M @ measured`` (column vectors).

    Wraps ``colour.characterisation.matrix_colour_correction``. ``"Cheung 2004"`` (3 terms) and
    ``"Finlayson 2015"`` (root-polynomial degree 1) both give a plain linear 3×3; they are the two
    exposure-invariant choices (a 3×3 commutes with a global gain).

    Args:
        measured: ``(N, 3)`` linear RGB as captured (N >= 3, e.g. 24 chart patches).
        reference: ``(N, 3)`` target linear RGB.
        method: one of :data:`CCM_METHODS`.
    Returns:
        ``M (3, 3)`` float64.
    """
    measured = _as_colours(measured, "measured colours")
    reference = _as_colours(reference, "reference colours")
    if measured.shape != reference.shape:
        raise ValueError(f"measured {measured.shape} and reference {reference.shape} colours differ in shape")
    if method == "Cheung 2004":
        kwargs: dict[str, Any] = {"terms": 3}
    elif method == "Finlayson 2015":
        kwargs = {"degree": 1}
    else:
        raise ValueError(f"unknown CCM method {method!r}; choose one of {CCM_METHODS}")
    M = colour.characterisation.matrix_colour_correction(measured, reference, method=method, **kwargs)
    return np.asarray(M, dtype=np.float64).reshape(3, 3)


def fit_affine_colour(measured: Any, reference: Any) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares affine colour map ``reference ≈ M @ measured + offset`` (Cheung 2004, 4 terms).

    Args: ``measured, reference (N, 3)`` with N >= 4. Returns ``(M (3, 3), offset (3,))``.
    """
    measured = _as_colours(measured, "measured colours")
    reference = _as_colours(reference, "reference colours")
    if measured.shape != reference.shape or measured.shape[0] < 4:
        raise ValueError(f"need matching (N>=4, 3) colours, got {measured.shape} and {reference.shape}")
    A = colour.characterisation.matrix_colour_correction(measured, reference, method="Cheung 2004", terms=4)
    A = np.asarray(A, dtype=np.float64).reshape(3, 4)
    return A[:, :3].copy(), A[:, 3].copy()


@dataclass(frozen=True)
class ColourError:
    """How far corrected colours are from their reference.

    rmse: root-mean-square difference in linear RGB. delta_e_mean / delta_e_max: CIE ΔE 2000 after
    converting both to CIE Lab (linear sRGB, D65).
    """

    rmse: float
    delta_e_mean: float
    delta_e_max: float


def linear_srgb_to_lab(rgb: Any) -> np.ndarray:
    """Linear sRGB ``(..., 3)`` → CIE Lab ``(..., 3)`` (D65 white), via colour-science."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        XYZ = colour.RGB_to_XYZ(np.asarray(rgb, dtype=np.float64), "sRGB")
        white = colour.RGB_COLOURSPACES["sRGB"].whitepoint
        return colour.XYZ_to_Lab(XYZ, white)


def ccm_error(measured: Any, reference: Any, M: Any, offset: Any = None) -> ColourError:
    """Score a colour matrix: apply ``M`` (and ``offset``) to ``measured (N, 3)``, compare to ``reference (N, 3)``."""
    measured = _as_colours(measured, "measured colours")
    reference = _as_colours(reference, "reference colours")
    corrected = apply_ccm(measured, M, offset)
    rmse = float(np.sqrt(np.mean((corrected - reference) ** 2)))
    delta_e = colour.delta_E(linear_srgb_to_lab(corrected), linear_srgb_to_lab(reference), method="CIE 2000")
    return ColourError(rmse=rmse, delta_e_mean=float(np.mean(delta_e)), delta_e_max=float(np.max(delta_e)))


# ---------------------------------------------------------------------------------------------------------
# Learned per-dataset matrix: the document (the dataset format decides where a dataset keeps it)
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LearnedColour:
    """A dataset's learned colour alignment, ``aligned = M @ rgb``: one matrix for the whole dataset and,
    for the cameras whose own colour response was fitted, one per camera (a rig's cameras differ)."""

    matrix: np.ndarray  # (3, 3), for cameras without their own
    cameras: Mapping[str, np.ndarray] = field(default_factory=dict)  # camera name -> (3, 3)

    def for_camera(self, camera: str) -> np.ndarray:
        """The (3, 3) matrix that aligns ``camera``'s images."""
        return self.cameras.get(camera, self.matrix)


def colour_alignment_text(
    M: Any, info: Mapping[str, Any] | None = None, cameras: Mapping[str, Any] | None = None
) -> str:
    """The learned alignment as its JSON document, keys sorted so the same inputs give the same bytes.

    ``M`` maps the dataset's linear RGB into the shared colour space, ``aligned = M @ rgb``; ``cameras``
    (name -> 3×3) does the same for the cameras fitted one by one, which then use theirs instead.
    ``info`` is free-form JSON (e.g. reference dataset, training step, residual).
    """
    M = _as_matrix(M, (3, 3), "learned colour matrix")
    per_camera = {
        str(name): _as_matrix(matrix, (3, 3), f"learned colour matrix of camera {name!r}")
        for name, matrix in (cameras or {}).items()
    }
    document = {
        "format": COLOUR_ALIGNMENT_FORMAT,
        "version": COLOUR_ALIGNMENT_VERSION,
        "convention": "aligned_linear_rgb = matrix @ dataset_linear_rgb (column vectors); a camera listed "
        "in 'cameras' uses its own matrix",
        "matrix": [[float(v) for v in row] for row in M],
        "cameras": {name: [[float(v) for v in row] for row in m] for name, m in per_camera.items()},
        "info": dict(info or {}),
    }
    try:
        return json.dumps(document, indent=2, sort_keys=True, allow_nan=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise ValueError(f"colour alignment info must be finite, JSON-serialisable values ({exc})") from exc


def _document_matrix(value: Any, where: str, field_name: str) -> np.ndarray:
    try:
        matrix = _as_matrix(value, (3, 3), f"field {field_name}")
    except (TypeError, ValueError) as exc:
        raise FileFormatError(f"{where}: {exc}") from exc
    return check_colour_matrix(matrix, f"{where}: field {field_name}")


def parse_colour_alignment(data: bytes, where: str) -> LearnedColour:
    """The :class:`LearnedColour` of a colour-alignment document; FileFormatError naming ``where`` when the
    document is not valid JSON, has another ``format`` or ``version``, or a matrix (``matrix``, each of
    ``cameras``) is not a finite, invertible 3×3."""
    try:
        document = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FileFormatError(
            f"{where}: not valid JSON ({exc}); delete it and re-run colour alignment"
        ) from exc
    if not isinstance(document, dict) or document.get("format") != COLOUR_ALIGNMENT_FORMAT:
        raise FileFormatError(f"{where}: field 'format' must be {COLOUR_ALIGNMENT_FORMAT!r}")
    if document.get("version") not in READABLE_COLOUR_ALIGNMENT_VERSIONS:
        raise FileFormatError(
            f"{where}: unsupported version {document.get('version')!r} (this toolkit reads "
            f"{', '.join(map(str, READABLE_COLOUR_ALIGNMENT_VERSIONS))})"
        )
    matrix = _document_matrix(document.get("matrix"), where, "'matrix'")
    cameras = document.get("cameras", {})
    if not isinstance(cameras, dict):
        raise FileFormatError(f"{where}: field 'cameras' must map camera names to 3×3 matrices")
    return LearnedColour(
        matrix,
        {str(name): _document_matrix(m, where, f"'cameras.{name}'") for name, m in cameras.items()},
    )
