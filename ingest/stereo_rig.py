"""Studio stereo rig captures (D3, flat-lit; SDFM-style, RAW + COLMAP + colour chart) -> a :class:`DatasetPlan`.

There is no public release of this kind of capture, so the layout is the project's own
(``docs/ingest.md``)::

    rig.json                                  optional: {"cameras", "stereo_pairs", "raw", "calibration",
                                              "colour_chart": {"frames"}, "units"}
    calibration/sparse/0/                     COLMAP model, binary (*.bin) or text (*.txt); one registered
                                              image "{camera}.dng" per camera
    calibration/colorchecker/{camera}.dng     one ColorChecker 24 frame per camera, same lights
    captures/{subject}/{camera}.dng           one RAW frame per subject and camera (frame 0)

Conventions:

* Cameras: ``ingest.calibration.from_colmap`` (COLMAP's pixel-centre offset of 0.5 removed, OPENCV
  distortion kept); a camera is named by its image's file stem. The model's world unit is the metre
  unless ``rig.json`` says ``"units": "mm"`` (or ``"cm"``); translations are converted here.
* RAW frames are codec ``dng-raw``: the runner demosaics them to linear camera RGB with
  :func:`relightanyone.ingest.decode.decode_bytes`. The chart frame of each camera goes through the very
  same decoding, then ``align.chart.fit_chart_correction`` (``cv2.mcc`` detection, Cheung-2004 3x3
  fitted with colour-science against the reference chart) gives the camera's matrix, applied in linear
  space. It maps the capture to reflectance-scaled linear sRGB, exposure included.
* A camera whose chart frame is missing, unreadable or not detected, or whose fit is far off the chart
  (mean ΔE 2000 above :data:`MAX_CHART_DELTA_E`) is refused for every subject, not guessed. The fit
  residual of every camera is reported in ``plan.found["chart_fit"]``.
* An unreadable or invalid COLMAP model stops planning with an error naming the folder (nothing could be
  correct); a capture file of a camera the model does not know, and a calibrated camera without a
  capture file for a subject, are refused.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from relightanyone.align.chart import ChartNotFoundError, fit_chart_correction
from relightanyone.align.colour import colour_matrix_problem
from relightanyone.format.schema import check_name
from relightanyone.ingest.adapter_common import adapter_plan
from relightanyone.ingest.calibration import CalibrationError, from_colmap, loads_json
from relightanyone.ingest.decode import DecodeError, decode_bytes
from relightanyone.ingest.records import (
    AdapterOptions,
    ColourCalibration,
    DatasetPlan,
    ImageRef,
    LayoutError,
    NativeCamera,
    Refusal,
    SourceView,
    SubjectPlan,
)

NAME = "stereo_rig"
KIND = "flat"
SOURCE_DATASET = "Stereo rig (SDFM-style studio capture)"
LICENCE = "studio capture; terms set by the lab that recorded it"

RIG_FILE = "rig.json"
DEFAULT_MODEL = "calibration/sparse/0"
DEFAULT_CHART_FRAMES = "calibration/colorchecker/{camera}.dng"
CAPTURES_DIR = "captures"
CODEC = "dng-raw"
FRAME = 0  # one exposure per subject and camera
CHART_METHOD = "Cheung 2004"
MAX_CHART_DELTA_E = 10.0  # a mean ΔE 2000 above this means a wrong detection, not a camera response
UNITS_TO_METRES = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}


def read_rig(src: Path) -> dict:
    """``rig.json`` as a dict (``{}`` when absent); ValueError naming the file when it is not a JSON object."""
    path = Path(src) / RIG_FILE
    if not path.is_file():
        return {}
    try:
        rig = loads_json(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise LayoutError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(rig, dict):
        raise LayoutError(f"{path}: expected a JSON object")
    return rig


def model_folder(src: Path, rig: dict) -> Path:
    """The COLMAP model folder: ``rig.json``'s ``calibration`` (relative to ``src``) or the default."""
    return Path(src) / str(rig.get("calibration", DEFAULT_MODEL))


def chart_pattern(rig: dict, where: str = RIG_FILE) -> str:
    """Path pattern of the chart frames relative to the rig folder, with a ``{camera}`` field."""
    chart = rig.get("colour_chart", {})
    pattern = chart.get("frames", DEFAULT_CHART_FRAMES) if isinstance(chart, dict) else DEFAULT_CHART_FRAMES
    if "{camera}" not in str(pattern):
        raise LayoutError(f"{where}: field 'colour_chart.frames' must contain '{{camera}}', got {pattern!r}")
    return str(pattern)


def metres_per_unit(rig: dict, where: str = RIG_FILE) -> float:
    """Metres per unit of the COLMAP model's world (``rig.json`` ``units``, metres by default)."""
    units = str(rig.get("units", "m"))
    if units not in UNITS_TO_METRES:
        raise LayoutError(f"{where}: field 'units' must be one of {sorted(UNITS_TO_METRES)}, got {units!r}")
    return UNITS_TO_METRES[units]


def detect(src: Path) -> str:
    """Layout version: ``"colmap-binary"`` or ``"colmap-text"``; raises LayoutError naming what is missing."""
    src = Path(src)
    if not src.is_dir():
        raise LayoutError(f"{src}: stereo rig folder not found")
    try:
        rig = read_rig(src)
    except ValueError as error:
        raise LayoutError(str(error)) from None
    model = model_folder(src, rig)
    if not model.is_dir():
        raise LayoutError(
            f"{model}: COLMAP model folder not found (expected cameras, images, points3D .bin or .txt)"
        )
    if not (src / CAPTURES_DIR).is_dir():
        raise LayoutError(f"{src / CAPTURES_DIR}: folder of captures/<subject>/<camera>.dng not found")
    for version, suffix in (("colmap-binary", ".bin"), ("colmap-text", ".txt")):
        if all((model / f"{part}{suffix}").is_file() for part in ("cameras", "images")):
            return version
    raise LayoutError(f"{model}: holds neither cameras.bin + images.bin nor cameras.txt + images.txt")


def read_cameras(model: Path, metres: float) -> dict[str, NativeCamera]:
    """Every registered camera of the COLMAP model at ``model``, by name (image file stem), in metres.

    Raises ``CalibrationError`` naming the folder and field when the model is unreadable or invalid.
    """

    rig = from_colmap(model)
    cameras: dict[str, NativeCamera] = {}
    for index, image_name in enumerate(rig.names):
        name = Path(image_name).stem
        if name in cameras:
            raise CalibrationError(model, f"images[{image_name}]", f"two registered images of camera {name}")
        w2c = rig.w2c[index].numpy().astype(np.float64)
        w2c[:3, 3] *= metres
        cameras[name] = NativeCamera(
            name=name,
            K=rig.K[index].numpy().astype(np.float64),
            w2c=w2c,
            dist=rig.dist[index, :5].numpy().astype(np.float64),
            width=int(rig.width[index]),
            height=int(rig.height[index]),
        )
    return cameras


def decode_raw(path: Path) -> np.ndarray:
    """``(H, W, 3)`` float32 linear camera RGB of a DNG, decoded exactly as the runner decodes ``dng-raw``."""

    try:
        data = Path(path).read_bytes()
    except OSError as error:
        raise DecodeError(f"{path}: cannot read ({error.strerror or error})") from None
    return decode_bytes(data, CODEC, str(path))


def fit_camera_chart(path: Path) -> tuple[np.ndarray, dict]:
    """Fit one camera's colour matrix from its chart frame.

    Returns ``(M (3, 3), residual)`` with ``reference ≈ M @ measured`` in linear RGB and the residual as
    ``{"rmse", "delta_e_mean", "delta_e_max"}`` on the 24 patches. Raises ``DecodeError`` (unreadable file)
    or ``ChartNotFoundError`` (no chart).
    """

    matrix, residual = fit_chart_correction(decode_raw(path), method=CHART_METHOD)
    return np.asarray(matrix, dtype=np.float64), {
        "rmse": round(residual.rmse, 6),
        "delta_e_mean": round(residual.delta_e_mean, 4),
        "delta_e_max": round(residual.delta_e_max, 4),
    }


def calibrate_cameras(
    src: Path, names: list[str], pattern: str
) -> tuple[dict[str, ColourCalibration], dict[str, dict], list[Refusal]]:
    """Chart-fitted colour calibration per camera, the fit residuals, and a refusal per failed camera."""

    calibrations, residuals, refusals = {}, {}, []
    for name in names:
        relative = pattern.format(camera=name)
        path = Path(src) / relative
        if not path.is_file():
            refusals.append(
                Refusal(
                    name, relative, "no colour chart frame for this camera; its colour cannot be calibrated"
                )
            )
            continue
        try:
            matrix, residual = fit_camera_chart(path)
        except (DecodeError, ChartNotFoundError, ValueError) as error:
            refusals.append(Refusal(name, relative, f"colour chart not usable: {error}"))
            continue
        residuals[name] = residual
        problem = colour_matrix_problem(matrix)
        if problem is not None:
            refusals.append(Refusal(name, relative, f"chart fit unusable: {problem}"))
            continue
        if residual["delta_e_mean"] > MAX_CHART_DELTA_E:
            refusals.append(
                Refusal(
                    name,
                    relative,
                    f"chart fit residual mean ΔE2000 {residual['delta_e_mean']:.1f} > "
                    f"{MAX_CHART_DELTA_E:g}: wrong detection or a damaged chart",
                )
            )
            continue
        calibrations[name] = ColourCalibration(
            matrix=matrix, space="linear", source=f"{relative} (ColorChecker 24, {CHART_METHOD})"
        )
    return calibrations, residuals, refusals


def worst_chart_fit(residuals: dict[str, dict]) -> str:
    """One line for the summary: the worst mean and max ΔE2000 over the cameras, and which cameras."""
    if not residuals:
        return "no chart fitted"
    mean_cam = max(residuals, key=lambda c: residuals[c]["delta_e_mean"])
    max_cam = max(residuals, key=lambda c: residuals[c]["delta_e_max"])
    return (
        f"mean ΔE2000 {residuals[mean_cam]['delta_e_mean']:.2f} ({mean_cam}), "
        f"max {residuals[max_cam]['delta_e_max']:.2f} ({max_cam})"
    )


def _plan_subject(
    folder: Path,
    src: Path,
    cameras: dict[str, NativeCamera],
    calibrations: dict[str, ColourCalibration],
    options: AdapterOptions,
) -> SubjectPlan:
    subject = check_name(folder.name, "subject", str(folder))
    plan = SubjectPlan(subject=subject, split=options.split_of(subject), views=[])
    plan.rig_w2c = {name: camera.w2c for name, camera in cameras.items()}
    present = {p.stem: p for p in sorted(folder.glob("*.dng"))}
    for name in sorted(set(present) - set(cameras)):
        if options.keeps_camera(name):
            source = present[name].relative_to(src).as_posix()
            plan.refusals.append(
                Refusal(f"{subject}/{name}", source, f"camera {name} is absent from the COLMAP model")
            )
    if not options.keeps_frame(FRAME):
        return plan
    for name in sorted(cameras):
        if not options.keeps_camera(name) or name not in calibrations:
            continue  # uncalibrated cameras are refused once, at the dataset level
        source = f"{CAPTURES_DIR}/{subject}/{name}.dng"
        if name not in present:
            plan.refusals.append(
                Refusal(f"{subject}/{name}", source, "missing frame: no RAW file for this calibrated camera")
            )
            continue
        plan.views.append(
            SourceView(
                subject=subject,
                frame=FRAME,
                camera=cameras[name],
                pattern="full",
                image=ImageRef(path=str(present[name]), codec=CODEC),
                colour=calibrations[name],
                source=source,
            )
        )
    return plan


def plan(src: Path, options: AdapterOptions) -> DatasetPlan:
    """Describe every selected subject's RAW frames under ``src`` (see the module docstring).

    Raises LayoutError when ``src`` is no stereo rig folder, and ``CalibrationError``/ValueError naming the
    file when the COLMAP model or ``rig.json`` is invalid.
    """
    src = Path(src).resolve()
    version = detect(src)
    rig = read_rig(src)
    metres = metres_per_unit(rig, str(src / RIG_FILE))
    cameras = read_cameras(model_folder(src, rig), metres)
    kept = [name for name in sorted(cameras) if options.keeps_camera(name)]
    calibrations, residuals, refusals = calibrate_cameras(src, kept, chart_pattern(rig, str(src / RIG_FILE)))
    folders = sorted(
        p for p in (src / CAPTURES_DIR).iterdir() if p.is_dir() and options.keeps_subject(p.name)
    )
    subjects = [_plan_subject(folder, src, cameras, calibrations, options) for folder in folders]
    pairs = rig.get("stereo_pairs", [])
    found = {
        "layout": version,
        "subjects": [s.subject for s in subjects],
        "cameras": kept,
        "calibrated_cameras": sorted(calibrations),
        "stereo_pairs": ["+".join(map(str, p)) for p in pairs if isinstance(p, list)]
        if isinstance(pairs, list)
        else [],
        "colmap_units": str(rig.get("units", "m")),
        "chart_fit": residuals,
        "chart_fit_worst": worst_chart_fit(residuals),
        "views": sum(len(s.views) for s in subjects),
    }
    return adapter_plan(
        NAME, KIND, SOURCE_DATASET, LICENCE, version, src, options, subjects, refusals=refusals, found=found
    )
