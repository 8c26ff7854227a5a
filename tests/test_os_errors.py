"""Operating-system faults (an unwritable output folder, a full disk) end a command with one line that names
the path and what to do, exit status 1 and no traceback; a re-run after the fault completes the work."""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

import pyarrow as pa
import pytest
from click.testing import CliRunner
from helpers.custom_capture import make_capture

from relightanyone import os_errors
from relightanyone.cli import cli
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.validate import validate_path
from relightanyone.ingest import custom

ROWS = 16  # 2 subjects x 2 frames x 4 cameras


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture(tmp_path_factory.mktemp("capture"))


def ingest(capture: Path, out: Path):
    return CliRunner().invoke(cli, ["ingest", "custom", str(capture), "--out", str(out), "--preset", "tiny"])


def error_line(result) -> str:
    """The one line of the failure (what was printed before it, such as ingest's findings, aside)."""
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert result.exit_code == 1 and len(errors) == 1 and "Traceback" not in result.output, result.output
    assert result.output.rstrip().endswith(errors[0])
    return errors[0]


def make_read_only(folder: Path, monkeypatch) -> None:
    """``folder`` read-only: by its mode, and, for root (whom modes do not stop), by refusing the temporary
    files the write probe creates there, as the kernel would for anyone else."""
    folder.chmod(0o555)
    if os.geteuid() != 0:
        return
    real_mkstemp = tempfile.mkstemp

    def refusing_mkstemp(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve() == folder.resolve():
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))
        return real_mkstemp(*args, dir=dir, **kwargs)

    monkeypatch.setattr(os_errors.tempfile, "mkstemp", refusing_mkstemp)


@pytest.mark.parametrize("fault", ["read-only folder", "file in place of a folder"])
def test_an_unwritable_output_stops_ingest_before_planning(capture, tmp_path, monkeypatch, fault):
    blocked = tmp_path / fault.replace(" ", "-")
    planned = []
    with monkeypatch.context() as patched:
        patched.setattr(custom, "plan", lambda *args: planned.append(args) or pytest.fail("planned"))
        if fault == "read-only folder":
            blocked.mkdir()
            make_read_only(blocked, patched)
            advice = "make it writable"
        else:
            blocked.write_bytes(b"not a folder")
            advice = "a file stands where a folder is needed"
        result = ingest(capture, blocked / "datasets")
    line = error_line(result)
    assert result.output.strip() == line  # found before anything was planned or printed
    assert line.startswith(f"Error: {blocked}: ") and advice in line
    assert planned == [] and list(tmp_path.iterdir()) == [blocked]
    # The fault removed, the same command completes.
    if fault == "read-only folder":
        blocked.chmod(0o755)
    else:
        blocked.unlink()
    assert ingest(capture, blocked / "datasets").exit_code == 0
    dataset = NormalizedDataset(blocked / "datasets" / "custom")
    assert len(dataset) == len(set(dataset.keys)) == ROWS


def test_the_write_probe_leaves_nothing_behind(tmp_path):
    os_errors.check_writable(tmp_path / "not" / "yet")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_is_one_line_naming_the_file_and_a_rerun_completes(capture, tmp_path, monkeypatch):
    out = tmp_path / "datasets"
    real_write = pa.ipc.RecordBatchStreamWriter.write_batch
    calls = []

    def filling_disk(self, batch, *args, **kwargs):
        calls.append(1)
        if len(calls) > 5:  # what pyarrow raises on a full disk: an errno, and no file name
            raise OSError(
                errno.ENOSPC, "Error writing bytes to file. Detail: [errno 28] No space left on device"
            )
        return real_write(self, batch, *args, **kwargs)

    with monkeypatch.context() as patched:
        patched.setattr(pa.ipc.RecordBatchStreamWriter, "write_batch", filling_disk)
        line = error_line(ingest(capture, out))
    assert f"{out / 'custom'}/" in line and ".tmp" in line and "No space left on device" in line
    assert "free space on that disk" in line
    result = ingest(capture, out)
    assert result.exit_code == 0, result.output
    dataset = NormalizedDataset(out / "custom")
    assert len(dataset) == len(set(dataset.keys)) == ROWS
    assert validate_path(out / "custom") == []


def test_run_finds_an_unwritable_stage_output_before_any_stage_starts(tmp_path):
    (tmp_path / "a-file").write_bytes(b"not a folder")
    marker = tmp_path / "ran"
    pipeline = tmp_path / "pipeline.yaml"
    pipeline.write_text(
        "stages:\n"
        f"  first:\n    command: [touch, {marker}]\n    output: {tmp_path / 'fine'}\n"
        f'  second:\n    command: ["true"]\n    output: {tmp_path / "a-file" / "out"}\n'
    )
    line = error_line(CliRunner().invoke(cli, ["run", str(pipeline)]))
    assert (
        line == f"Error: {tmp_path / 'a-file'}: Not a directory; {os_errors.OS_ERROR_ADVICE[errno.ENOTDIR]}"
    )
    assert not marker.exists()


def test_a_write_error_that_names_no_file_is_given_the_file(tmp_path):
    """/dev/full fails every write with ENOSPC and, as any failed write, names no file."""
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    with pytest.raises(OSError) as caught, os_errors.naming_file(tmp_path / "part.arrow"):
        with open("/dev/full", "wb") as handle:
            handle.write(b"x" * 100)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(tmp_path / "part.arrow")
    assert "No space left on device" in os_errors.os_error_line(caught.value)
