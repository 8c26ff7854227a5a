"""What an ingest tells its user: every refusal with its reason in the dry run, the image sizes and fit
residuals it read, a non-zero exit when no row is written, and lines only where they apply."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from helpers.custom_capture import make_capture

from relightanyone.cli import cli
from relightanyone.ingest.runner import listed_values
from relightanyone.synth.template import make_template, write_obj


@pytest.fixture
def capture(tmp_path) -> Path:
    return make_capture(tmp_path / "capture")


def ingest_args(capture: Path, out: Path, *extra: str) -> list[str]:
    return ["ingest", "custom", str(capture), "--out", str(out), "--preset", "tiny", "--template",
            str(capture / "template.obj"), *extra]  # fmt: skip


def test_dry_run_prints_every_refusal_sizes_and_residuals(capture, tmp_path):
    noise = np.zeros((128, 96, 3), np.uint8)
    for k in range(7):  # seven cameras absent from cameras.json: more than a real run lists
        cv2.imwrite(str(capture / "images" / "s1" / "000000" / f"x{k}.png"), noise)
    cv2.imwrite(str(capture / "images" / "s2" / "000001" / "c1.png"), np.zeros((64, 48, 3), np.uint8))
    result = CliRunner().invoke(cli, ingest_args(capture, tmp_path / "out", "--dry-run"))
    assert result.exit_code == 0, result.output
    for k in range(7):
        assert f"camera 'x{k}' is not in" in result.output
    assert "image is 48x64 but cameras.json gives camera c1 96x128" in result.output
    assert "image sizes: 96x128 (15 views)" in result.output
    assert "template fit: worst residual" in result.output
    # Meshes shipped in the native world: no tracker cameras to agree with.
    assert "native vs tracker" not in result.output and "agree to" not in result.output
    assert "dry run: nothing written" in result.output and not (tmp_path / "out").exists()


def test_cameras_line_respects_the_selection(capture, tmp_path):
    result = CliRunner().invoke(
        cli, ingest_args(capture, tmp_path / "out", "--dry-run", "--cameras", "c0,c2")
    )
    assert result.exit_code == 0, result.output
    assert "  cameras: c0, c2\n" in result.output


def test_long_lists_end_with_how_many_more():
    text = listed_values([f"cam{k:02d}" for k in range(30)])
    assert text.endswith("cam24 ... and 5 more") and ", ," not in text and not text.endswith(", ")
    assert listed_values(["a", "b"]) == "a, b"
    assert listed_values({"s1": [1, 2]}) == "s1: 1, 2"


def test_meshes_in_mm_declared_metres_are_flagged(capture, tmp_path):
    template = make_template(12)
    for mesh in (capture / "meshes").rglob("*.obj"):
        write_obj(mesh, template.vertices * 1000.0, template.faces)
    result = CliRunner().invoke(cli, ingest_args(capture, tmp_path / "out", "--dry-run"))
    assert "is too large for a fit of the same head" in result.output and "mm vs m" in result.output
    assert "worst residual" not in result.output


def test_no_aligned_frame_stops_before_writing(capture, tmp_path):
    for mesh in (capture / "meshes").rglob("*.obj"):
        mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")  # wrong vertex count: no frame aligns
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ingest_args(capture, out))
    assert result.exit_code == 1
    assert "nothing to write" in result.output and "000000.obj" in result.output
    assert not (out / "custom").exists()


def test_every_view_quarantined_exits_non_zero_and_validate_fails(capture, tmp_path):
    for image in (capture / "images").rglob("*.png"):
        image.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ingest_args(capture, out))
    assert result.exit_code == 1
    assert "no row was written" in result.output and "quarantine.jsonl" in result.output
    validated = CliRunner().invoke(cli, ["validate", str(out / "custom")])
    assert validated.exit_code != 0 and "no image row" in validated.output
