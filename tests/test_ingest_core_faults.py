"""Bad input and faults: corrupt files, unsafe zips, missing cameras and meshes, bad calibrations, the CLI.

Inputs are small hand-made custom captures (``helpers.custom_capture``), so nothing here needs the
synthetic world's renderer.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from helpers.custom_capture import SIZE, dataset_bytes, ingest, make_capture
from PIL import AvifImagePlugin, Image

from relightanyone.align.colour import srgb_to_linear
from relightanyone.cli import cli
from relightanyone.format.overlay import reprojection_overlays
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest import custom
from relightanyone.ingest.decode import DecodeError, TaskDecoder, set_decoder_threads
from relightanyone.ingest.records import AdapterOptions, ImageRef, LayoutError
from relightanyone.ingest.tracking import read_vhap_subject


@pytest.fixture
def capture(tmp_path) -> Path:
    return make_capture(tmp_path / "capture")


def test_clean_capture_is_written_with_provenance(capture, tmp_path):
    summary = ingest(capture, tmp_path / "out")
    assert (summary.rows, summary.quarantined) == (16, 0)
    dataset = NormalizedDataset(summary.path)
    row = dataset.row(dataset.keys[0])
    assert (row.width, row.height) == (128, 128)
    assert row.source.startswith("images/") and len(row.source_sha256) == 64
    assert row.source_sha256 == hashlib.sha256((capture / row.source).read_bytes()).hexdigest()
    manifest = json.loads((summary.path / "manifest.json").read_text())
    template_sha = hashlib.sha256((capture / "template.obj").read_bytes()).hexdigest()
    assert manifest["template_mesh_id"] == template_sha
    assert manifest["provenance"]["tracker"] == "meshes shipped with the capture"
    assert (summary.path / "template.obj").read_bytes() == (capture / "template.obj").read_bytes()
    assert len(dataset.meshes()) == 4
    # The reprojection overlay draws the mesh where the mask is (4x upscaled drawing).
    key = "custom/s1/000001/c2/full"
    (overlay,) = reprojection_overlays(summary.path, keys=[key])
    _, _, mask = dataset.decoded(key)
    # The outline is drawn anti-aliased over a 4x nearest-neighbour upscale: a stored pixel was drawn on when
    # its 4x4 block is no longer uniform, and drawn in the head's colour (not the neck's orange, which
    # outlines the neck below the mask) when one of its pixels is green-dominant.
    blocks = overlay.astype(np.int16).reshape(128, 4, 128, 4, 3)
    changed = (blocks.max(axis=(1, 3)) != blocks.min(axis=(1, 3))).any(axis=-1)
    red, green, blue = blocks[..., 0], blocks[..., 1], blocks[..., 2]
    greenish = ((green > red + 60) & (green > blue + 60)).any(axis=(1, 3))
    drawn = changed & greenish
    near_mask = cv2.dilate((mask > 0.5).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    # A few blended pixels may fall just past the dilated mask; a misplaced mesh would put most of them there.
    outside = (drawn & ~near_mask).sum()
    assert drawn.sum() > 60 and outside <= 0.02 * drawn.sum(), (drawn.sum(), outside)


def test_corrupt_image_missing_camera_and_bad_mesh_are_quarantined(capture, tmp_path):
    (capture / "images" / "s1" / "000000" / "c0.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    (capture / "images" / "s1" / "000000" / "c9.png").write_bytes(b"")  # camera absent from cameras.json
    mesh = capture / "meshes" / "s2" / "000001.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")  # wrong vertex count
    summary = ingest(capture, tmp_path / "out")
    assert summary.rows == 16 - 1 - 4
    assert summary.quarantined == 1 + 1 + 4
    entries = {e.item: e for e in NormalizedDataset(summary.path).quarantine()}
    assert "c0.png" in entries["s1/000000/c0/full"].reason
    assert entries["s1/000000/c0/full"].stage == "decode"
    assert "cameras.json" in entries["s1/000000/c9/full"].reason
    bad_mesh = entries["s2/000001/c2/full"]
    assert "000001.obj" in bad_mesh.reason and "vertices" in bad_mesh.reason
    assert summary.reasons == {"decode": 1, "plan": 1, "align": 4}


def test_quarantine_reasons_are_the_same_bytes_on_every_run(capture, tmp_path):
    image = capture / "images" / "s2" / "000001" / "c3.png"
    image.unlink()
    image.with_suffix(".avif").write_bytes(b"\x00\x00\x00\x1cftypavif" + bytes(64))  # corrupt AVIF
    first = ingest(capture, tmp_path / "first")
    second = ingest(capture, tmp_path / "second")
    (entry,) = NormalizedDataset(first.path).quarantine()
    assert "c3.avif" in entry.reason and "not a readable AVIF image" in entry.reason
    assert " at 0x" not in entry.reason, entry.reason
    assert (first.path / "quarantine.jsonl").read_bytes() == (second.path / "quarantine.jsonl").read_bytes()


def test_alpha_maps_multiply_the_mesh_mask(capture, tmp_path):
    folder = capture / "alpha" / "s1" / "000000"
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "c1.png"), np.zeros((SIZE[1], SIZE[0]), np.uint8))
    dataset = NormalizedDataset(ingest(capture, tmp_path / "out").path)
    _, _, cut = dataset.decoded("custom/s1/000000/c1/full")
    _, _, kept = dataset.decoded("custom/s1/000000/c2/full")
    assert cut.max() == 0.0 and kept.mean() > 0.1


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["cameras"]["c1"].pop("K"), "camera 'c1': missing key 'K'"),
        (lambda d: d.pop("units"), "missing key 'units'"),
        (lambda d: d["cameras"]["c2"]["w2c"][0].__setitem__(0, float("nan")), "camera 'c2' key 'w2c'"),
        (lambda d: d["cameras"]["c3"].__setitem__("w2c", np.zeros((4, 4)).tolist()), "camera 'c3' key 'w2c'"),
        (lambda d: d.__setitem__("units", "inch"), "'units' must be one of"),
        (
            lambda d: d.__setitem__("colour_matrices", {"c1": np.zeros((3, 3)).tolist()}),
            "colour_matrices['c1']: the colour matrix is singular",
        ),
        (
            lambda d: d.__setitem__("colour_matrices", {"c2": [[1, 0, 0], [0, 1, 0], [1, 1, 0]]}),
            "colour_matrices['c2']: the colour matrix is singular",
        ),
    ],
)
def test_bad_calibration_names_file_camera_and_key(capture, edit, message):
    path = capture / "cameras.json"
    document = json.loads(path.read_text())
    edit(document)
    path.write_text(json.dumps(document))
    with pytest.raises(LayoutError) as error:
        custom.plan(capture, AdapterOptions())
    assert message in str(error.value) and "cameras.json" in str(error.value)


def _transforms(**changes) -> str:
    """A one-camera VHAP ``transforms.json`` text with ``changes`` applied to its frame."""
    frame = {"camera_id": "c0", "transform_matrix": np.eye(4).tolist(), "fl_x": 100.0, "cx": 50.0}
    frame.update({"cy": 50.0, "w": 100, "h": 100, "timestep_index": 0, **changes})
    return json.dumps({"frames": [frame]}, indent=1)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (_transforms()[:200], "not valid JSON"),  # truncated
        (_transforms(fl_x=float("nan")), "field 'frames[0].fl_x': contains NaN"),
        (_transforms(transform_matrix=[[float("nan")] * 4] * 4), "frames[0].transform_matrix"),
        (_transforms(timestep_index_original=float("nan")), "field 'timestep_index_original'"),
        (_transforms(timestep_index="first"), "field 'timestep_index' is not a frame number"),
        (_transforms(mesh_path=7), "field 'mesh_path' must be a path"),
        ("[]", "expected an object"),
    ],
)
def test_tracking_errors_name_the_file(tmp_path, text, message):
    (tmp_path / "transforms.json").write_text(text)
    with pytest.raises(ValueError) as error:
        read_vhap_subject(tmp_path)
    assert str(error.value).startswith(str(tmp_path / "transforms.json")), error.value
    assert message in str(error.value) and "<dict>" not in str(error.value), error.value


def test_missing_layout_pieces_are_named(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(LayoutError, match="cameras.json, meshes"):
        custom.detect(tmp_path)


def test_unsafe_truncated_and_incomplete_zips(tmp_path):
    archive = tmp_path / "cam1.zip"
    with zipfile.ZipFile(archive, "w") as handle:
        handle.writestr("cam1/000001.png", b"x")
        handle.writestr("../x", b"y")
    with TaskDecoder(tmp_path) as decoder:
        with pytest.raises(DecodeError, match="outside the archive"):
            decoder.read_bytes(ImageRef("cam1.zip", "png-srgb", member="../x"))
        with pytest.raises(DecodeError, match="no member 'cam1/000002.png'"):
            decoder.read_bytes(ImageRef("cam1.zip", "png-srgb", member="cam1/000002.png"))
    truncated = tmp_path / "cut.zip"
    truncated.write_bytes(archive.read_bytes()[: archive.stat().st_size // 3])
    with TaskDecoder(tmp_path) as decoder, pytest.raises(DecodeError, match="cut.zip.*truncated"):
        decoder.read_bytes(ImageRef("cut.zip", "png-srgb", member="cam1/000001.png"))


@pytest.mark.parametrize("codec", ["exr-linear", "avif-srgb", "dng-raw", "jpg-srgb"])
def test_corrupt_files_of_every_codec_raise_naming_the_file(tmp_path, codec):
    (tmp_path / "bad.bin").write_bytes(b"\x00\x01garbage" * 50)
    with TaskDecoder(tmp_path) as decoder, pytest.raises(DecodeError, match="bad.bin"):
        decoder.decode(ImageRef("bad.bin", codec))


def _write_mp4(path: Path, frames: list[np.ndarray], crf: int, pix_fmt: str) -> None:
    """H.264 video of ``frames`` (each ``(H, W, 3)`` uint8 RGB) at 25 fps."""
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=25, options={"crf": str(crf)})
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = pix_fmt
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_video_frames_are_decoded_in_one_pass_and_corrupt_videos_refused(tmp_path):
    frames = [np.full((32, 48, 3), 40 * i, np.uint8) for i in range(5)]
    _write_mp4(tmp_path / "cam.mp4", frames, crf=0, pix_fmt="yuv444p")
    refs = [ImageRef("cam.mp4", "mp4-frame", frame_index=i) for i in (3, 1)]
    with TaskDecoder(tmp_path) as decoder:
        decoder.prefetch_videos(refs)
        images = [decoder.decode(ref)[0] for ref in refs]
        with pytest.raises(DecodeError, match="no frame 9"):
            decoder.decode(ImageRef("cam.mp4", "mp4-frame", frame_index=9))
    for image, index in zip(images, (3, 1), strict=True):
        assert np.allclose(image, srgb_to_linear(np.float32(40 * index / 255)), atol=2e-3)
    (tmp_path / "bad.mp4").write_bytes(b"not a video" * 10)
    with TaskDecoder(tmp_path) as decoder, pytest.raises(DecodeError, match="bad.mp4"):
        decoder.decode(ImageRef("bad.mp4", "mp4-frame", frame_index=0))


def test_cli_dry_run_prints_findings_and_writes_nothing(capture, tmp_path):
    out = tmp_path / "out"
    args = [
        "custom",
        str(capture),
        "--out",
        str(out),
        "--preset",
        "tiny",
        "--template",
        str(capture / "template.obj"),
    ]
    result = CliRunner().invoke(cli, ["ingest", *args, "--dry-run"])
    assert result.exit_code == 0, result.output
    assert "16 views" in result.output and "MB" in result.output and "dry run" in result.output
    assert not out.exists()
    result = CliRunner().invoke(cli, ["ingest", *args, "--subjects", "s2", "--cameras", "c0,c1,c2"])
    assert result.exit_code == 0, result.output
    assert "6 rows written, 0 quarantined" in result.output
    missing = CliRunner().invoke(cli, ["ingest", "custom", str(tmp_path), "--out", str(out)])
    assert missing.exit_code != 0 and "missing cameras.json" in missing.output


def test_local_pool_gives_the_same_bytes_as_one_process(capture, tmp_path):
    one = ingest(capture, tmp_path / "one", workers=1)
    two = ingest(capture, tmp_path / "two", workers=2)
    assert dataset_bytes(one.path) == dataset_bytes(two.path)


def test_single_threaded_decoders_give_the_same_pixels(tmp_path):
    """Tasks decode AVIF and video with one thread; the pixels must not depend on the thread count."""
    rng = np.random.default_rng(4)
    frames = [(rng.random((48, 64, 3)) * 255).astype(np.uint8) for _ in range(3)]
    Image.fromarray(frames[0]).save(tmp_path / "view.avif", quality=90)
    _write_mp4(tmp_path / "cam.mp4", frames, crf=18, pix_fmt="yuv420p")
    refs = [ImageRef("view.avif", "avif-srgb")] + [
        ImageRef("cam.mp4", "mp4-frame", frame_index=i) for i in range(3)
    ]

    def decode_all() -> list[np.ndarray]:
        with TaskDecoder(tmp_path) as decoder:
            decoder.prefetch_videos(refs[1:])
            return [decoder.decode(ref)[0] for ref in refs]

    try:
        set_decoder_threads(avif=0, video=0)
        default = decode_all()
        set_decoder_threads(avif=1, video=1)
        assert AvifImagePlugin.DEFAULT_MAX_THREADS == 1
        single = decode_all()
    finally:
        set_decoder_threads(avif=0, video=0)
    for a, b in zip(default, single, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="threads"):
        set_decoder_threads(avif=-1, video=1)


def test_an_empty_image_is_refused_while_planning_so_a_dry_run_lists_it(capture, tmp_path):
    (capture / "images" / "s1" / "000001" / "c2.png").write_bytes(b"")
    args = ["ingest", "custom", str(capture), "--out", str(tmp_path / "out"), "--preset", "tiny", "--dry-run"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "1 refused while planning" in result.output
    assert "s1/000001/c2/full: c2.png: the file is empty" in result.output
    doctor = CliRunner().invoke(cli, ["doctor", "custom", str(capture)])
    assert doctor.exit_code == 1 and "convention checks: all passed" in doctor.output
    assert "doctor: 1 items refused while planning or aligning" in doctor.output
