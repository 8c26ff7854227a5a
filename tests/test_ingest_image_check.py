"""The image checks on the rendered custom capture: images flipped, swapped between cameras or frames,
in BGR order, of another tracking or pose, or with the head in black shadow; each named, or passed
silently when the capture is clean.

The captures are :mod:`helpers.checks_capture`'s; the dataset-level convention checks are in
``test_ingest_checks.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.checks_capture import (
    ingest_custom,
    make_rendered_capture,
    other_pose_mesh,
    quarantine,
    run,
)

from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest.checks import subsample
from relightanyone.ingest.decode import TaskDecoder
from relightanyone.ingest.image_check import hull_indices, hull_mask, image_foreground
from relightanyone.ingest.image_decisions import mismatched_frames
from relightanyone.render.mesh import read_obj
from relightanyone.synth.capture import look_at_w2c
from relightanyone.synth.template import write_obj

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def capture(tmp_path) -> Path:
    return make_rendered_capture(tmp_path / "capture")


def test_swapped_images_quarantine_both_views_naming_the_pair(capture, tmp_path):
    for frame in ("000000", "000001"):
        folder = capture / "images" / "s1" / frame
        first, second = (folder / "c0.png").read_bytes(), (folder / "c2.png").read_bytes()
        (folder / "c0.png").write_bytes(second)
        (folder / "c2.png").write_bytes(first)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = {entry["item"]: entry["reason"] for entry in quarantine(tmp_path / "out")}
    expected = {f"s1/00000{f}/{c}/full" for f in (0, 1) for c in ("c0", "c2")}
    assert set(refused) == expected
    assert all("cameras c0 and c2 look swapped" in reason for reason in refused.values())


def in_bgr_order(capture: Path) -> None:
    """Every image written from an RGB array by ``cv2.imwrite`` (which expects BGR): red and blue swapped."""
    for path in (capture / "images").rglob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path))[..., ::-1])


def test_images_in_bgr_order_refuse_the_subject_with_the_fix(capture, tmp_path):
    in_bgr_order(capture)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 1, result.output  # no row was written
    refused = quarantine(tmp_path / "out")
    assert len(refused) == 15
    for entry in refused:
        assert entry["reason"].startswith("check colour-order: subject s1: on the head, blue is above red in")
        assert "write them in RGB order" in entry["reason"]
    doctor = run("doctor", "custom", capture)
    assert doctor.exit_code == 1 and "[override: --accept-check colour-order]" in doctor.output


def test_colour_order_can_be_accepted_for_a_capture_under_blue_light(capture, tmp_path):
    in_bgr_order(capture)
    result = ingest_custom(capture, tmp_path / "out", "--accept-check", "colour-order")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15


def test_upside_down_image_is_quarantined_with_its_orientation(capture, tmp_path):
    path = capture / "images" / "s1" / "000000" / "c3.png"
    cv2.imwrite(str(path), cv2.imread(str(path))[::-1, ::-1])
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    [entry] = quarantine(tmp_path / "out")
    assert entry["item"] == "s1/000000/c3/full" and entry["stage"] == "check"
    assert "upside down relative to its mask" in entry["reason"]


def test_mesh_of_another_pose_quarantines_the_frame(capture, tmp_path):
    other_pose_mesh(capture)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = quarantine(tmp_path / "out")
    assert {e["item"] for e in refused} == {f"s1/000001/c{k}/full" for k in range(5)}
    assert all("mesh of another frame or head pose" in e["reason"] for e in refused)


def swap_frame_images(capture: Path, first: str, second: str, cameras=("c0", "c1", "c2", "c3", "c4")) -> None:
    """The images of two frames exchanged for ``cameras``, as when image folders are numbered wrongly."""
    for camera in cameras:
        a, b = (capture / "images" / "s1" / frame / f"{camera}.png" for frame in (first, second))
        a_bytes, b_bytes = a.read_bytes(), b.read_bytes()
        a.write_bytes(b_bytes)
        b.write_bytes(a_bytes)


def test_images_of_two_frames_exchanged_refuse_both_frames_as_mispaired(capture, tmp_path):
    """Frames 0 and 2 (6 degrees, 8 mm apart) exchange their images. Most views still agree with the wrong
    mesh within the held-back margin, and the frame comparison sees two of three frames disagree without
    telling which; a view of each frame showing the other's head names the exchange, and every view of
    both frames is refused, rows already written included."""
    swap_frame_images(capture, "000000", "000002")
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = {e["item"]: e["reason"] for e in quarantine(tmp_path / "out")}
    assert set(refused) == {f"s1/00000{f}/c{k}/full" for f in (0, 2) for k in range(5)}
    for item, reason in refused.items():
        other = "2" if item.split("/")[1] == "000000" else "0"
        assert f"judged images show the head of frame {other}, and frame {other}'s images that of" in reason
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 5  # frame 1's images are its own


def test_one_image_of_another_frame_is_named_with_that_frame(capture, tmp_path):
    folder = capture / "images" / "s1"
    (folder / "000000" / "c3.png").write_bytes((folder / "000002" / "c3.png").read_bytes())
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    [entry] = quarantine(tmp_path / "out")
    assert entry["item"] == "s1/000000/c3/full"
    assert "the image of camera c3 shows the head of frame 2" in entry["reason"]


def test_view_partly_off_its_foreground_in_a_good_frame_is_written_after_all(capture, tmp_path, monkeypatch):
    """A view held back as doubtful (part of the head dark, as under black hair) is released when its
    frame agrees with the subject's other frames."""
    path = capture / "images" / "s1" / "000001" / "c2.png"
    image = cv2.imread(str(path))
    rows = np.flatnonzero(image.max(axis=(1, 2)) > 0)
    image[rows[0] : rows[0] + (rows[-1] - rows[0]) // 8] = 0
    cv2.imwrite(str(path), image)
    decoded: list[str] = []
    decode = TaskDecoder.decode
    monkeypatch.setattr(
        TaskDecoder, "decode", lambda self, ref: decoded.append(ref.label) or decode(self, ref)
    )
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    dataset = NormalizedDataset(tmp_path / "out" / "custom")
    assert len(dataset) == 15
    # The held view's row was kept, not decoded again, and is the row an ingest that holds nothing writes.
    assert len(decoded) == len(set(decoded)) == 15, decoded
    unheld = ingest_custom(capture, tmp_path / "unheld", "--accept-check", "silhouette")
    assert unheld.exit_code == 0, unheld.output
    key = next(k for k in dataset.keys if "/c2/" in k and "/000001/" in k)
    unheld_row = NormalizedDataset(tmp_path / "unheld" / "custom").row(key)
    assert dataset.row(key).to_arrow_dict() == unheld_row.to_arrow_dict()


def test_head_half_in_black_shadow_passes_with_no_finding(capture, tmp_path):
    """Skin in deep shadow is as black as the backdrop: with one side of the head pure black in every view
    of a frame, the head is half off the foreground, yet the foreground lies on the head."""
    for path in sorted((capture / "images" / "s1" / "000001").glob("*.png")):
        image = cv2.imread(str(path))
        columns = np.flatnonzero(image.max(axis=(0, 2)) > 0)
        image[:, (columns[0] + columns[-1]) // 2 :] = 0
        cv2.imwrite(str(path), image)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15


def test_mismatched_frames_need_other_frames_to_compare_with():
    shares = {0: [1.0, 0.99, 1.0], 1: [0.9, 0.93, 0.91], 2: [1.0, 0.98]}
    bad, baseline = mismatched_frames(shares)
    assert set(bad) == {1} and baseline == pytest.approx(0.99)
    assert mismatched_frames({1: [0.9, 0.93, 0.91]})[0] == {}
    assert mismatched_frames({0: [0.95, 0.96], 1: [0.95, 0.94]})[0] == {}


def move_meshes(capture: Path, offset: tuple[float, float, float]) -> None:
    """Every frame's mesh moved by ``offset`` (m) in the capture's world: the tracking of other images
    (another sequence of the subject, the head a few centimetres elsewhere)."""
    for path in sorted((capture / "meshes").rglob("*.obj")):
        vertices, faces = read_obj(path)
        write_obj(path, vertices + np.asarray(offset), faces)


def test_tracking_of_other_images_refuses_the_whole_subject(capture, tmp_path):
    move_meshes(capture, (0.06, 0.0, 0.04))
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 1 and "no row was written" in result.output, result.output
    assert "most frequent: check silhouette: subject s1: " in result.output
    refused = quarantine(tmp_path / "out")
    assert len(refused) == 15
    assert all("the tracking is not of these images" in e["reason"] for e in refused)
    assert all("--sequence" in e["reason"] and e["stage"] == "check" for e in refused)
    # A dataset without rows has nothing to overlay: said in one line, no traceback.
    overlay = run("inspect", tmp_path / "out" / "custom", "--overlay", tmp_path / "overlay.png")
    assert overlay.exit_code == 1 and "has no image rows to draw" in overlay.output
    assert "Traceback" not in overlay.output


def test_a_camera_wrong_in_every_frame_is_refused_as_a_whole(capture, tmp_path):
    """c3's rotation is 6 degrees off: it still faces the head, so only its images show the fault, in
    every frame, whatever each view's own verdict guesses."""
    path = capture / "cameras.json"
    document = json.loads(path.read_text())
    angle = np.radians(6.0)
    turn = np.eye(4)
    turn[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    document["cameras"]["c3"]["w2c"] = (turn @ np.array(document["cameras"]["c3"]["w2c"])).tolist()
    path.write_text(json.dumps(document))
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    refused = {e["item"]: e["reason"] for e in quarantine(tmp_path / "out")}
    assert set(refused) == {f"s1/00000{f}/c3/full" for f in range(3)}
    assert all("camera c3" in r and "a fault of the camera itself" in r for r in refused.values())
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 12
    # The image check runs while writing; the summary names what it quarantined.
    assert "each image is checked as it is written" in result.output
    assert "a fault of the camera itself" in result.output and "(3 views)" in result.output


def test_an_image_of_another_camera_in_a_second_file_is_not_written_for_the_first(capture, tmp_path):
    """Two files for one view (``c0.png`` and ``c0.jpg``, the second showing c2's view): the first in
    order is kept, and its own row is the one written."""
    folder = capture / "images" / "s1" / "000000"
    cv2.imwrite(str(folder / "c0.jpg"), cv2.imread(str(folder / "c2.png")), [cv2.IMWRITE_JPEG_QUALITY, 100])
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    dataset = NormalizedDataset(tmp_path / "out" / "custom")
    row = dataset.row(next(k for k in dataset.keys if "/000000/c0/" in k))
    [entry] = [e for e in quarantine(tmp_path / "out") if e["item"] == "s1/000000/c0/full"]
    assert row.source != entry["source"]
    assert row.source.endswith(("c0.png", "c0.jpg")) and entry["source"].endswith(("c0.png", "c0.jpg"))


def test_background_is_found_when_the_head_reaches_the_border_away_from_its_mask():
    image = np.zeros((40, 30, 3), np.float32)
    image[10:30, 0:12] = 0.6  # the head, touching the left border
    expected = np.zeros((40, 30), bool)
    expected[10:30, 18:30] = True  # where the mesh says it is: the image is mirrored
    foreground = image_foreground(image, expected)
    assert foreground is not None and foreground.sum() == 20 * 12 and foreground[10:30, 0:12].all()
    image[:, :, 1] = np.linspace(0, 0.5, 30)[None]  # a border with no dominant colour: cannot tell
    assert image_foreground(image, expected) is None


def test_outline_is_the_hull_of_every_vertex():
    """The 3D hull's vertices outline a head exactly as all of its vertices do; an evenly spaced subsample
    misses the extreme ones (here the outline of 150 of them covers clearly less)."""
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(6000, 3))
    radii = np.where(rng.random(6000) < 0.5, 1.0, rng.uniform(0.5, 0.95, 6000))[
        :, None
    ]  # a surface and inside
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * radii * [0.08, 0.11, 0.09]
    K = np.array([[300.0, 0, 47.5], [0, 300.0, 63.5], [0, 0, 1]])
    w2c = look_at_w2c(np.array([0.3, 0.1, 0.8]), np.zeros(3))
    everything = hull_mask(points, K, w2c, (96, 128))
    hull = points[hull_indices(points)]
    assert np.array_equal(hull_mask(hull, K, w2c, (96, 128)), everything)
    assert len(hull) < len(points) / 2
    assert hull_mask(subsample(points, 150), K, w2c, (96, 128)).sum() < 0.95 * everything.sum()


def test_head_mostly_black_like_dark_hair_passes_with_no_finding(capture, tmp_path):
    """The upper 60 % of the head as black as the backdrop in every view: the foreground still lies on
    the head's outline, so nothing is refused (no view, camera or subject)."""
    for path in sorted((capture / "images" / "s1").rglob("*.png")):
        image = cv2.imread(str(path))
        rows = np.flatnonzero(image.max(axis=(1, 2)) > 0)
        image[: rows[0] + int(0.6 * (rows[-1] - rows[0]))] = 0
        cv2.imwrite(str(path), image)
    result = ingest_custom(capture, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert quarantine(tmp_path / "out") == []
    assert len(NormalizedDataset(tmp_path / "out" / "custom")) == 15
