"""D3: an SDFM-style stereo capture rig (there is no public SDFM release).

Eight cameras in four stereo pairs in front of the face, lit by four frontal flashes, writing 12-bit
Bayer RAW. The layout under ``<out>/stereo_rig/`` is this project's choice, modelled on a studio
rig calibrated with COLMAP and a colour chart::

    rig.json                                  {"cameras": [...], "stereo_pairs": [[left, right], ...],
                                               "raw": {"bits": 12, "cfa": "RGGB", "black": 256, "white": 4095}}
    calibration/sparse/0/cameras.bin ...      COLMAP binary model (pycolmap): OPENCV cameras, one image per
                                              camera named "{camera}.dng", world in metres
    calibration/colorchecker/{camera}.dng     one ColorChecker frame per camera (chart alone, facing the rig,
                                              same flashes)
    captures/{subject}/{camera}.dng           one frame per subject and camera

COLMAP puts the centre of the top-left pixel at (0.5, 0.5), so its principal point is the OpenCV one
plus 0.5. The DNG pixel values are ``black + M @ true_linear * (white - black)`` (plus a little sensor
noise) mosaicked RGGB, M being the camera's colour response; a 3x3 fitted from the chart frame against
the colour-science ColorChecker reference (linear sRGB reflectances) undoes it.
"""

from __future__ import annotations

import json
from pathlib import Path

import colour
import numpy as np
import pycolmap
from pidng.core import RAW2DNG, DNGTags, Tag
from pidng.defs import CalibrationIlluminant, CFAPattern, DNGVersion, Orientation, PhotometricInterpretation
from scipy.spatial.transform import Rotation

from relightanyone.synth.capture import (
    HEAD_AIM_POINT,
    apply_colour_response,
    focal_for_field,
    frontal_flashes,
    intrinsics,
    look_at_w2c,
    native_w2c,
    random_colour_responses,
    random_world_from_canonical,
    report_progress,
    spherical_direction,
    srgb_encode,
    to_uint8,
)
from relightanyone.synth.presets import Preset
from relightanyone.synth.raytrace import PointLights, Scene, SynthCamera, render, textured_quad
from relightanyone.synth.template import HeadTemplate
from relightanyone.synth.truth import DatasetTruth, RenderedRig

NATIVE_DIR = "stereo_rig"
RAW_BITS = 12
BLACK_LEVEL = 256
WHITE_LEVEL = 2**RAW_BITS - 1
NOISE_SIGMA = 0.002  # read noise, fraction of the white level
EXPOSURE = 0.5  # recorded value of a white Lambertian surface at the head under the flashes (RAW headroom)
CHART_NAME = "ColorChecker24 - After November 2014"
CHART_SIZE_M = (0.2794, 0.2159)  # X-Rite ColorChecker Classic card, width x height
CHART_TEXTURE = 512
PAIR_AZIMUTHS_DEG = (-48.0, -16.0, 16.0, 48.0)
BASELINE_M = 0.12


def chart_reference_linear_srgb() -> np.ndarray:
    """(24, 3) linear sRGB (D65) reflectances of the ColorChecker patches, row-major from dark skin."""
    chart = colour.CCS_COLOURCHECKERS[CHART_NAME]
    xyY = np.array(list(chart.data.values()))
    return colour.XYZ_to_RGB(
        colour.xyY_to_XYZ(xyY),
        "sRGB",
        illuminant=chart.illuminant,
        chromatic_adaptation_transform="Bradford",
        apply_cctf_encoding=False,
    ).clip(0.0, 1.0)


def chart_texture(width: int = CHART_TEXTURE) -> np.ndarray:
    """(H, W, 3) float32 albedo of the chart card, row 0 along its top edge: 4x6 patches on a black card."""
    height = int(round(width * CHART_SIZE_M[1] / CHART_SIZE_M[0]))
    reference = chart_reference_linear_srgb()
    texture = np.full((height, width, 3), 0.03, dtype=np.float32)
    # Card layout in metres (Classic card: ~4 cm patches, ~0.6 cm gaps, centred).
    patch, gap = 0.040, 0.0064
    x_margin = (CHART_SIZE_M[0] - 6 * patch - 5 * gap) / 2
    y_margin = (CHART_SIZE_M[1] - 4 * patch - 3 * gap) / 2
    texels_per_m = width / CHART_SIZE_M[0]
    for row in range(4):
        for col in range(6):
            x0 = (x_margin + col * (patch + gap)) * texels_per_m
            y0 = (y_margin + row * (patch + gap)) * texels_per_m
            size = patch * texels_per_m
            r0, r1 = int(round(y0)), int(round(y0 + size))
            c0, c1 = int(round(x0)), int(round(x0 + size))
            texture[r0:r1, c0:c1] = reference[row * 6 + col]
    return texture


def chart_scene(rng: np.random.Generator) -> Scene:
    """The chart card held in front of the face, facing the rig (+z), as the subject would hold it.

    Facing the middle of the symmetric flash arc keeps its illumination nearly uniform, so that a single
    3x3 fitted to its patches describes the camera; a few degrees of random hold angle are added.
    """
    rotation = Rotation.from_rotvec(rng.uniform(-0.05, 0.05, 3)).as_matrix()
    right, down = rotation @ np.array([1.0, 0.0, 0.0]), rotation @ np.array([0.0, -1.0, 0.0])
    centre = HEAD_AIM_POINT + np.array([0.0, 0.0, 0.04])
    half_w, half_h = CHART_SIZE_M[0] / 2, CHART_SIZE_M[1] / 2
    corners = np.array(
        [
            centre - half_w * right - half_h * down,
            centre + half_w * right - half_h * down,
            centre + half_w * right + half_h * down,
            centre - half_w * right + half_h * down,
        ]
    )
    return textured_quad(corners, chart_texture(), specular_intensity=0.0, roughness=1.0)


def subject_names(rng: np.random.Generator, count: int) -> list[str]:
    """Session-style subject folders P001, P002, ... (the rig has no public naming)."""
    return [f"P{k + 1:03d}" for k in range(count)]


def make_cameras(preset: Preset, rng: np.random.Generator) -> list[SynthCamera]:
    """Four horizontal stereo pairs (left, right) spread over the front, landscape images."""
    size = preset.d3
    width, height = size.image_size
    if size.cameras != 2 * len(PAIR_AZIMUTHS_DEG):
        raise ValueError(
            f"the D3 rig has {2 * len(PAIR_AZIMUTHS_DEG)} cameras, preset asks for {size.cameras}"
        )
    cameras = []
    for pair, azimuth in enumerate(PAIR_AZIMUTHS_DEG):
        distance = rng.uniform(0.85, 0.95)
        elevation = np.deg2rad(rng.uniform(-4.0, 12.0))
        centre = HEAD_AIM_POINT + distance * spherical_direction(np.deg2rad(azimuth), elevation)
        towards = HEAD_AIM_POINT - centre
        side = np.cross(towards, [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        for k, sign in enumerate((-1.0, 1.0)):
            eye = centre + sign * BASELINE_M / 2 * side
            w2c = look_at_w2c(eye, HEAD_AIM_POINT + rng.uniform(-0.01, 0.01, 3))
            focal = focal_for_field(height, distance, 0.34) * rng.uniform(0.98, 1.02)
            K = intrinsics(focal, width, height, rng.uniform(-1.5, 1.5, 2))
            dist = np.array([rng.uniform(-0.06, 0.0), rng.uniform(0.0, 0.04), 0.0, 0.0, 0.0])
            cameras.append(SynthCamera(f"cam{2 * pair + k:02d}", K, w2c, width, height, dist))
    return cameras


def flash_lights(count: int) -> PointLights:
    """``count`` frontal flashes on a 1 m arc around the cameras (alternating above and below)."""
    return frontal_flashes(count, 40.0, 22.0, -8.0, radius=1.0, mean_cosine=0.8)


def mosaic_rggb(recorded: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) recorded linear [0, 1] -> (H, W) uint16 12-bit RGGB Bayer codes with black level and noise."""
    height, width = recorded.shape[:2]
    plane = np.empty((height, width), dtype=np.float64)
    plane[0::2, 0::2] = recorded[0::2, 0::2, 0]
    plane[0::2, 1::2] = recorded[0::2, 1::2, 1]
    plane[1::2, 0::2] = recorded[1::2, 0::2, 1]
    plane[1::2, 1::2] = recorded[1::2, 1::2, 2]
    plane = plane + rng.normal(0.0, NOISE_SIGMA, size=plane.shape)
    codes = BLACK_LEVEL + plane * (WHITE_LEVEL - BLACK_LEVEL)
    return np.clip(np.round(codes), 0, WHITE_LEVEL).astype(np.uint16)


def dng_bytes(bayer: np.ndarray, camera_name: str) -> bytes:
    """12-bit uncompressed DNG (pidng) with the black/white levels and the RGGB CFA tags rawpy reads."""
    height, width = bayer.shape
    tags = DNGTags()
    tags.set(Tag.ImageWidth, width)
    tags.set(Tag.ImageLength, height)
    tags.set(Tag.TileWidth, width)
    tags.set(Tag.TileLength, height)
    tags.set(Tag.Orientation, Orientation.Horizontal)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, RAW_BITS)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, CFAPattern.RGGB)
    tags.set(Tag.BlackLevel, BLACK_LEVEL)
    tags.set(Tag.WhiteLevel, WHITE_LEVEL)
    # Identity camera matrix: the file makes no colour claim; the chart frame calibrates colour.
    identity = [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]]
    tags.set(Tag.ColorMatrix1, identity)
    tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    tags.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    tags.set(Tag.Make, "relightanyone-synth")
    tags.set(Tag.Model, f"stereo-rig {camera_name}")
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    writer = RAW2DNG()
    writer.options(tags, path="", compress=False)
    return bytes(writer.convert(bayer))


def write_colmap(folder: Path, cameras: list[SynthCamera], world_from_canonical: np.ndarray) -> None:
    """COLMAP binary model: one OPENCV camera (COLMAP pixel convention) and one posed image per camera."""
    reconstruction = pycolmap.Reconstruction()
    for index, cam in enumerate(cameras, start=1):
        fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2] + 0.5, cam.K[1, 2] + 0.5
        params = [fx, fy, cx, cy, cam.dist[0], cam.dist[1], cam.dist[2], cam.dist[3]]
        reconstruction.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="OPENCV", width=cam.width, height=cam.height, params=params, camera_id=index
            )
        )
        w2c = native_w2c(cam.w2c, world_from_canonical)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        image = pycolmap.Image(name=f"{cam.name}.dng", camera_id=index, image_id=index)
        reconstruction.add_image_with_trivial_frame(image, pose)
    folder.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(folder))


def generate(
    out_root: Path,
    preset: Preset,
    template: HeadTemplate,
    subjects: list,
    splits: dict[str, str],
    rng: np.random.Generator,
    progress=None,
) -> DatasetTruth:
    """Write the D3 rig (calibration, chart frames, one RAW frame per subject and camera)."""
    size = preset.d3
    root = Path(out_root) / NATIVE_DIR
    world_from_canonical = random_world_from_canonical(rng, scale=1.0, offset_range=0.5)
    cameras = make_cameras(preset, rng)
    lights = flash_lights(size.lights)
    responses = random_colour_responses(rng, cameras, gain_spread=0.3, crosstalk=0.08)
    root.mkdir(parents=True, exist_ok=True)
    rig = {
        "cameras": [cam.name for cam in cameras],
        "stereo_pairs": [[cameras[2 * k].name, cameras[2 * k + 1].name] for k in range(len(cameras) // 2)],
        "raw": {"bits": RAW_BITS, "cfa": "RGGB", "black": BLACK_LEVEL, "white": WHITE_LEVEL},
        "calibration": "calibration/sparse/0",
        "colour_chart": {"name": CHART_NAME, "frames": "calibration/colorchecker/{camera}.dng"},
    }
    (root / "rig.json").write_text(json.dumps(rig, indent=2))
    write_colmap(root / "calibration" / "sparse" / "0", cameras, world_from_canonical)

    def write_raw(path: Path, image: np.ndarray, cam: SynthCamera) -> None:
        recorded = apply_colour_response(image * EXPOSURE, responses[cam.name])
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(dng_bytes(mosaic_rggb(recorded, rng), cam.name))

    for cam in cameras:
        result = render(chart_scene(rng), cam, lights, supersampling=preset.supersampling)
        write_raw(root / "calibration" / "colorchecker" / f"{cam.name}.dng", result.image, cam)
        report_progress(progress)

    head_poses: dict[tuple[str, int], np.ndarray] = {}
    for subject in subjects:
        head_poses[(subject.name, 0)] = np.eye(4)
        scene = Scene.from_subject(template, subject, head_pose=np.eye(4))
        for cam in cameras:
            result = render(scene, cam, lights, supersampling=preset.supersampling)
            write_raw(root / "captures" / subject.name / f"{cam.name}.dng", result.image, cam)
            report_progress(progress)

    extra = {
        "chart_reference_linear_srgb": chart_reference_linear_srgb().tolist(),
        "raw_normalisation": "recorded_linear = (dng - black) / (white - black)",
        "colmap_principal_point": "OpenCV cx, cy + 0.5",
        "frame_key": "0 (one frame per subject)",
    }
    colour_response = {name: response * EXPOSURE for name, response in responses.items()}
    rig = RenderedRig(world_from_canonical, cameras, lights, colour_response)
    return DatasetTruth.of_rig("d3", "stereo-rig", NATIVE_DIR, rig, head_poses, splits, extra)


def expected_renders(preset: Preset) -> int:
    size = preset.d3
    return size.cameras + size.subjects * size.cameras


def decode_dng(path: Path) -> np.ndarray:
    """(H, W, 3) recorded linear RGB of a rig DNG: rawpy demosaic in camera space, black/white normalised."""
    import rawpy

    with rawpy.imread(str(path)) as raw:
        rgb = raw.postprocess(
            gamma=(1, 1),
            no_auto_bright=True,
            output_bps=16,
            output_color=rawpy.ColorSpace.raw,
            use_camera_wb=False,
            user_wb=[1.0, 1.0, 1.0, 1.0],
            user_flip=0,
        )
    return rgb.astype(np.float64) / 65535.0


def preview_images(native_root: Path, count: int) -> list[tuple[str, np.ndarray]]:
    """A chart frame and the first subject's views, decoded from the DNGs and sRGB-encoded."""

    root = Path(native_root)
    paths = sorted((root / "calibration" / "colorchecker").glob("*.dng"))[:1]
    subjects = sorted(p for p in (root / "captures").glob("*") if p.is_dir())
    if subjects:
        paths += sorted(subjects[0].glob("*.dng"))[: max(count - 1, 0)]
    return [(f"{p.parent.name}/{p.stem}", to_uint8(srgb_encode(decode_dng(p) * 1.5))) for p in paths]
