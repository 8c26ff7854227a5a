"""Stereo rig (D3) and NeRSemble (D4) end to end through the shared ingest runner, judged by the answers.

Colour is checked where it matters: the ingested pixel of a true surface point (a template vertex of the
subject's true shape, projected with the row's canonical camera) against the ground-truth linear
radiance at the same point of the native image (the native file decoded by the world's own decoders,
its recorded colour undone with ``truth.colour_response``, sampled where the truth camera drew it).
"""

from __future__ import annotations

import json
import shutil

import av
import cv2
import numpy as np
import pytest
from helpers.small_worlds import make_world, reduced_preset
from helpers.synth_judge import project, subject_vertices

from relightanyone.align.colour import srgb_to_linear
from relightanyone.align.geometry import transform_points
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest import nersemble, runner, stereo_rig
from relightanyone.ingest.records import AdapterOptions
from relightanyone.synth.d3_stereo_rig import decode_dng
from relightanyone.synth.presets import DatasetSize
from relightanyone.synth.truth import DatasetTruth

MINI = reduced_preset(
    d3=DatasetSize(train_subjects=1, test_subjects=0, cameras=8, image_size=(160, 120), lights=4),
    d4=DatasetSize(train_subjects=1, test_subjects=0, cameras=4, image_size=(64, 96), frames=2, lights=8),
)
D3_CAMERAS = ("cam00", "cam03", "cam04", "cam07")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("world_d3d4_runner"), MINI, seed=11, datasets=("d3", "d4"))


def ingest(world, plan, dataset: str, out):
    return runner.ingest_dataset(
        plan,
        world / "tracking" / dataset,
        out,
        preset="tiny",
        workers=1,
        progress=False,
        template=world / "answers" / "template" / "template.obj",
    )


def sample(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N, C) bilinear samples of ``image (H, W, C)`` at ``pixels (N, 2)`` (pixel centres at integers)."""
    grid = pixels.astype(np.float32).reshape(-1, 1, 2)
    values = cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32), grid[..., 0], grid[..., 1], cv2.INTER_LINEAR
    )
    return values.reshape(len(pixels), -1)


def surface_colours(world, dataset: str, truth: DatasetTruth, row, image, mask, native_linear):
    """Ingested and true linear RGB ``(N, 3)`` each, at the subject's vertices well inside the row's mask."""
    vertices = subject_vertices(world, dataset, row.subject)
    stored = project(row.K, row.w2c, np.zeros(5), vertices)
    camera = truth.cameras[row.camera]
    posed = transform_points(truth.head_poses[(row.subject, row.frame)], vertices)
    native = project(camera.K, camera.w2c, camera.dist, posed)
    inside = cv2.erode((mask > 0.99).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(np.float32)
    keep = (stored >= 2).all(axis=1) & (stored[:, 0] < row.width - 3) & (stored[:, 1] < row.height - 3)
    keep &= sample(inside[:, :, None], np.clip(stored, 0, row.width - 1))[:, 0] > 0.99
    assert keep.sum() > 50, row.key
    true_linear = native_linear @ np.linalg.inv(truth.colour_response[row.camera]).T
    return sample(image, stored[keep]), sample(true_linear, native[keep])


def geometry_error_px(world, dataset: str, truth: DatasetTruth, row) -> float:
    """Largest distance (stored pixels) between the true vertices projected with the row's canonical camera
    and where the renderer drew them, carried through the row's undistort + crop + resize."""
    vertices = subject_vertices(world, dataset, row.subject)
    got = project(row.K, row.w2c, np.zeros(5), vertices)
    camera = truth.cameras[row.camera]
    posed = transform_points(truth.head_poses[(row.subject, row.frame)], vertices)
    undistorted = project(camera.K, camera.w2c, np.zeros(5), posed)
    x0, y0, x1, _ = row.crop
    scale = row.width / (x1 - x0)
    expected = (undistorted - [x0, y0] + 0.5) * scale - 0.5
    return float(np.abs(got - expected).max())


def test_d4_ingested_pixels_match_true_radiance(world, tmp_path):
    truth = DatasetTruth.load(world / "answers" / "d4" / "truth.json")
    plan = nersemble.plan(world / "nersemble", AdapterOptions())
    summary = ingest(world, plan, "d4", tmp_path)
    assert summary.rows == plan.view_count == 8 and summary.quarantined == 0
    dataset = NormalizedDataset(summary.path)
    errors = []
    for key in dataset.keys:
        row, image, mask = dataset.decoded(key)
        video, frame = row.source.split("#frame=")
        with av.open(str(world / "nersemble" / video)) as container:
            codes = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)][int(frame)]
        got, true = surface_colours(world, "d4", truth, row, image, mask, srgb_to_linear(codes / 255.0))
        errors.append(np.median(np.abs(got - true).sum(axis=1) / true.sum(axis=1)))
        assert geometry_error_px(world, "d4", truth, row) < 0.5, key
        np.testing.assert_allclose(
            row.colour_matrix[:, :3], np.linalg.inv(truth.colour_response[row.camera]), atol=1e-9
        )
        assert not row.colour_matrix[:, 3].any()  # a 3×3 calibration: no offset
    assert max(errors) < 0.01, errors  # video rounding and resampling only: the file CCM is exact


def test_d4_per_camera_3x4_colour_matrices_are_recorded_as_applied(world, tmp_path):
    # NeRSemble v2 ships one 3×4 CCM per camera (an offset column added after the matrix, in linear light).
    plan = nersemble.plan(world / "nersemble", AdapterOptions(frames=(0,)))
    plain = NormalizedDataset(ingest(world, plan, "d4", tmp_path / "plain").path)
    src = shutil.copytree(world / "nersemble", tmp_path / "nersemble")
    offsets = {}
    for colour_file in src.glob(f"*/{nersemble.V2_COLOUR}"):
        ccms = json.loads(colour_file.read_text())
        for k, serial in enumerate(sorted(ccms)):
            offsets[serial] = np.array([0.01, 0.02, 0.03]) * (k + 1)
            ccms[serial] = np.hstack([np.asarray(ccms[serial])[:, :3], offsets[serial][:, None]]).tolist()
        colour_file.write_text(json.dumps(ccms))
    plan = nersemble.plan(src, AdapterOptions(frames=(0,)))
    affine = NormalizedDataset(ingest(world, plan, "d4", tmp_path / "affine").path)
    assert affine.keys == plain.keys and len(affine.keys) == 4
    for key in affine.keys:
        row, image, _ = affine.decoded(key)
        plain_row, plain_image, _ = plain.decoded(key)
        np.testing.assert_array_equal(row.colour_matrix[:, :3], plain_row.colour_matrix[:, :3])
        np.testing.assert_array_equal(row.colour_matrix[:, 3], offsets[row.camera])
        # The recorded matrix is the one applied: the stored pixels moved by exactly its offset column
        # (where the source fills the pixel and the 3×3 result is not clipped at 0), up to float16.
        lit = row.valid_pixels() & (plain_image > 0.05).all(axis=2)
        assert lit.sum() > 100, key
        shift = image[lit] - plain_image[lit]
        np.testing.assert_allclose(shift, np.broadcast_to(offsets[row.camera], shift.shape), atol=2e-3)


def test_d3_ingested_pixels_match_true_radiance_up_to_chart_exposure(world, tmp_path):
    truth = DatasetTruth.load(world / "answers" / "d3" / "truth.json")
    plan = stereo_rig.plan(world / "stereo_rig", AdapterOptions(cameras=D3_CAMERAS))
    summary = ingest(world, plan, "d3", tmp_path)
    assert summary.rows == plan.view_count == len(D3_CAMERAS) and summary.quarantined == 0
    dataset = NormalizedDataset(summary.path)
    scales, chroma = [], []
    for key in dataset.keys:
        row, image, mask = dataset.decoded(key)
        got, true = surface_colours(
            world, "d3", truth, row, image, mask, decode_dng(world / "stereo_rig" / row.source)
        )
        assert geometry_error_px(world, "d3", truth, row) < 0.5, key
        scales.append(np.median(got.sum(axis=1)) / np.median(true.sum(axis=1)))
        chroma.append(
            np.median(np.abs(got / got.sum(1, keepdims=True) - true / true.sum(1, keepdims=True)).max(axis=1))
        )
    # The chart fixes colour exactly and exposure up to the chart's irradiance, the same for every camera.
    assert max(chroma) < 0.01, chroma
    assert np.ptp(scales) < 0.05 and 0.8 < np.mean(scales) < 1.05, scales


def test_d3_corrupt_raw_is_quarantined_and_the_rest_written(world, tmp_path):
    src = shutil.copytree(world / "stereo_rig", tmp_path / "stereo_rig")
    broken = src / "captures/P001/cam03.dng"
    broken.write_bytes(broken.read_bytes()[:300])
    plan = stereo_rig.plan(src, AdapterOptions(cameras=D3_CAMERAS))
    summary = ingest(world, plan, "d3", tmp_path / "out")
    assert summary.rows == len(D3_CAMERAS) - 1 and summary.quarantined == 1
    (entry,) = NormalizedDataset(summary.path).quarantine()
    assert entry.source == "captures/P001/cam03.dng" and "cam03.dng" in entry.reason


# A v1 release of the same captures: 16-bit PNGs holding the *calibrated* colour, run through the inverse
# of a display-space affine, so that the v1 loaders' affine gives back the calibrated colour; intrinsics
# for frames twice the PNGs; alpha maps (one camera's empty, to see that alpha reaches the mask).
V1_AFFINE = np.array([[1.04, 0.02, 0.0, 0.01], [-0.01, 0.97, 0.02, 0.0], [0.0, 0.01, 1.02, -0.01]])
EMPTY_ALPHA_CAMERA = "222200046"


def write_calibrated_v1(world, out):
    import json

    from relightanyone.align.colour import linear_to_srgb, read_nersemble_colour_calibration

    for participant in sorted(p for p in (world / "nersemble").iterdir() if p.is_dir()):
        target = out / participant.name
        target.mkdir(parents=True)
        params = json.loads((participant / "calibration/camera_params.json").read_text())
        K = np.array(params["intrinsics"])
        K[:2, :2] *= 2.0
        K[:2, 2] = (K[:2, 2] + 0.5) * 2.0 - 0.5
        (target / "camera_params.json").write_text(
            json.dumps(
                {
                    **params,
                    "intrinsics": K.tolist(),
                    "width": 2 * params["width"],
                    "height": 2 * params["height"],
                }
            )
        )
        ccms = read_nersemble_colour_calibration(participant / "calibration/color_calibration.json")
        for video in sorted((participant / "sequences/EXP-1-head/images").glob("cam_*.mp4")):
            serial = video.stem[len("cam_") :]
            with av.open(str(video)) as container:
                frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
            for t, codes in enumerate(frames):
                calibrated = linear_to_srgb(np.clip(srgb_to_linear(codes / 255.0) @ ccms[serial][0].T, 0, 1))
                stored = (calibrated - V1_AFFINE[:, 3]) @ np.linalg.inv(V1_AFFINE[:, :3])
                folder = target / f"sequences/EXP-1-head/frame_{t:05d}"
                for name in ("images-2x-73fps", "alpha_map-73fps"):
                    (folder / name).mkdir(parents=True, exist_ok=True)
                png = np.round(np.clip(stored, 0, 1) * 65535).astype(np.uint16)
                cv2.imwrite(str(folder / f"images-2x-73fps/cam_{serial}.png"), png[:, :, ::-1])
                alpha = np.full(codes.shape[:2], 0 if serial == EMPTY_ALPHA_CAMERA else 255, np.uint8)
                cv2.imwrite(str(folder / f"alpha_map-73fps/cam_{serial}.png"), alpha)
            affine = target / f"annotations/EXP-1-head/color_correction/{serial}.npy"
            affine.parent.mkdir(parents=True, exist_ok=True)
            np.save(affine, V1_AFFINE)
    return out


def test_d4_v1_through_the_runner_matches_true_radiance(world, tmp_path):
    truth = DatasetTruth.load(world / "answers" / "d4" / "truth.json")
    src = write_calibrated_v1(world, tmp_path / "v1")
    plan = nersemble.plan(src, AdapterOptions(frames=(1,)))
    assert plan.layout_version == "v1" and plan.found["downsample_factor"] == [2]
    summary = ingest(world, plan, "d4", tmp_path / "out")
    assert summary.rows == plan.view_count == 4 and summary.quarantined == 0
    dataset = NormalizedDataset(summary.path)
    errors = []
    for key in dataset.keys:
        row, image, mask = dataset.decoded(key)
        if row.camera == EMPTY_ALPHA_CAMERA:
            assert mask.max() == 0  # the alpha map multiplies the mesh silhouette
            continue
        video = world / "nersemble" / row.subject / "sequences/EXP-1-head/images" / f"cam_{row.camera}.mp4"
        with av.open(str(video)) as container:
            codes = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)][row.frame]
        got, true = surface_colours(world, "d4", truth, row, image, mask, srgb_to_linear(codes / 255.0))
        errors.append(np.median(np.abs(got - true).sum(axis=1) / true.sum(axis=1)))
    assert len(errors) == 3 and max(errors) < 0.01, errors
