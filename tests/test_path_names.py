"""Names that become path components: a subject, camera or pattern that is not one safe file name is refused
where it enters (an adapter) and again where a path is built from it (an export), and `validate` reports it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.format import schema
from relightanyone.format.examples import example_rows
from relightanyone.format.schema import DatasetInfo, Provenance
from relightanyone.format.shards import ShardWriter

# Each one can be a folder name on Linux; each is refused for a different clause of the rule.
BAD_FOLDER_NAMES = ("..", ".hidden", "back\\slash", "tab\there", "x" * 129)
# Names a hand-written index may hold (no file system stands in the way there).
BAD_INDEX_NAMES = ("..", "../up", ".", "a/b", "nul\x00byte")


def files_under(folder: Path) -> set[str]:
    return {
        os.path.relpath(os.path.join(top, name), folder)
        for top, _, names in os.walk(folder)
        for name in names
    }


def write_ava_capture(src: Path, subject: str) -> Path:
    """An Ava-256-layout capture folder whose subject id is ``subject`` (enough for detection and planning)."""
    capture = src / f"20230101--1200--{subject}"
    (capture / "decoder" / "image").mkdir(parents=True)
    (capture / "decoder" / "camera_calibration.json").write_text("{}")
    return capture


@pytest.mark.parametrize("subject", BAD_FOLDER_NAMES)
def test_ingest_refuses_a_capture_whose_subject_is_not_a_safe_name(tmp_path, subject):
    src, tracking, out = tmp_path / "src", tmp_path / "tracking", tmp_path / "out"
    capture = write_ava_capture(src, subject)
    tracking.mkdir()
    result = CliRunner().invoke(
        cli, ["ingest", "ava256", str(src), "--tracking", str(tracking), "--out", str(out)]
    )
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert "Traceback" not in result.output and len(lines) == 1, result.output
    assert str(capture) in lines[0] and f"subject name {subject!r}" in lines[0] and "rename it" in lines[0]
    assert not out.exists()


def write_dataset_with_subject(root: Path, subject: str, monkeypatch) -> Path:
    """A complete dataset whose rows, index and meshes hold ``subject``, written past the name check (as a
    crafted or foreign dataset would be)."""
    with monkeypatch.context() as patched:
        patched.setattr(schema, "check_name", lambda name, what, where: name)
        info = DatasetInfo("demo", "flat", "flame", "flat", Provenance("test", "research"), "cfg")
        writer = ShardWriter(root / "demo", info)
        writer.begin()
        with writer.part("crafted") as part:
            for row in example_rows("demo", (subject,), cameras=1, patterns=("full",)):
                part.add(row)
        writer.commit()
    return root / "demo"


@pytest.mark.parametrize("subject", BAD_INDEX_NAMES)
def test_export_of_a_dataset_with_an_unsafe_subject_writes_nothing_outside_out(
    tmp_path, subject, monkeypatch
):
    dataset = write_dataset_with_subject(tmp_path / "data", subject, monkeypatch)
    parent = tmp_path / "exports"
    out = parent / "deep" / "out"
    out.mkdir(parents=True)
    before = files_under(tmp_path)
    result = CliRunner().invoke(cli, ["export-dataset", str(dataset), "--out", str(out)])
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert "Traceback" not in result.output and len(lines) == 1, result.output
    assert f"subject name {subject!r}" in lines[0] and "index.arrow" in lines[0]
    assert files_under(tmp_path) == before  # nothing written anywhere, in --out or beside it


@pytest.mark.parametrize("subject", BAD_INDEX_NAMES)
def test_validate_reports_an_unsafe_subject(tmp_path, subject, monkeypatch):
    dataset = write_dataset_with_subject(tmp_path, subject, monkeypatch)
    result = CliRunner().invoke(cli, ["validate", str(dataset)])
    assert result.exit_code == 1
    assert f"subject name {subject!r}" in result.output and "images-00000.arrow row 0" in result.output


def test_a_safe_dataset_still_exports(tmp_path, monkeypatch):
    dataset = write_dataset_with_subject(tmp_path / "data", "s000", monkeypatch)
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["export-dataset", str(dataset), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert (out / "s000" / "000000" / "cam00" / "full.exr").is_file()
    assert CliRunner().invoke(cli, ["validate", str(dataset)]).exit_code == 0
