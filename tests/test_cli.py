"""The ``relightanyone`` command as a whole: one error boundary for every command, the help listing, and
options shared across layers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from relightanyone.cli import COMMAND_ORDER, RelightAnyoneGroup, cli, failure_line
from relightanyone.cli_options import PRESET_NAMES


def _bad_inputs(tmp: Path) -> list[tuple[list[str], str]]:
    """(arguments, the file or folder the one-line error must name) for failures of several layers."""
    empty = tmp / "empty"
    empty.mkdir()
    (tmp / "bad.yaml").write_text("vars: [\n")
    (tmp / "splits.json").write_text("{not json")
    (tmp / "garbage.avatar").write_bytes(b"not an avatar")
    (tmp / "a-file").write_text("")
    world = tmp / "world"
    world.mkdir()
    (world / "unrelated.txt").write_text("")
    out = str(tmp / "out")
    return [
        (["validate", str(tmp / "missing")], str(tmp / "missing")),  # a path argument naming nothing
        (["ingest", "custom", str(empty), "--out", out], str(empty)),  # LayoutError
        (["ingest", "custom", str(empty), "--splits", str(tmp / "splits.json"), "--out", out], "splits.json"),
        (["run", str(tmp / "bad.yaml")], "bad.yaml"),  # PipelineError
        (["train", "stage1", "--data", str(empty), "--out", out], str(empty)),  # IncompleteDatasetError
        (["relight", str(tmp / "garbage.avatar"), "--olat", "0", "--out", out], "garbage.avatar"),
        (["relight", str(empty), "--olat", "0", "--out", out], str(empty)),  # a folder without avatars
        (["report", "--out", str(tmp / "a-file" / "report"), "--quiet"], str(tmp / "a-file")),  # OSError
        (["synth", "--out", str(world)], str(world)),  # synth's own WorldError
    ]


def test_expected_failures_are_one_line_naming_the_file_with_status_1(tmp_path):
    for args, named in _bad_inputs(tmp_path):
        result = CliRunner().invoke(cli, args)
        lines = result.stderr.strip().splitlines()
        assert result.exit_code == 1 and isinstance(result.exception, SystemExit), (args, result.output)
        assert len(lines) == 1 and lines[0].startswith("Error: ") and named in lines[0], (args, result.stderr)
        assert "Traceback" not in result.output, args


def test_a_bug_keeps_its_traceback():
    group = RelightAnyoneGroup("demo")

    @group.command("broken")
    def broken() -> None:
        raise KeyError("a bug, not bad input")

    result = CliRunner().invoke(group, ["broken"])
    assert isinstance(result.exception, KeyError)


def test_failure_line_names_the_file_of_an_os_error_and_what_to_do():
    assert failure_line(PermissionError(13, "Permission denied", "/data/out")) == (
        "/data/out: Permission denied; make it writable (permissions, owner) or write somewhere else"
    )
    assert failure_line(OSError(18, "Invalid cross-device link", "a.tmp", None, "b")) == (
        "a.tmp -> b: Invalid cross-device link"
    )
    # pyarrow's full disk names no file: the folder the command writes stands in for it.
    full = OSError(28, "Error writing bytes to file. Detail: [errno 28] No space left on device")
    assert failure_line(full, "/data/out") == (
        "/data/out (being written): Error writing bytes to file. Detail: [errno 28] No space left on device; "
        "free space on that disk or write somewhere else, then run the command again (it resumes)"
    )
    assert (
        failure_line(FileNotFoundError("tracking folder t does not exist"))
        == "tracking folder t does not exist"
    )
    assert failure_line(ValueError("x.json: bad\n  detail")) == "x.json: bad; detail"


def test_help_lists_the_commands_in_data_flow_order_without_heavy_imports():
    result = CliRunner().invoke(cli, ["--help"])
    listed = [line.split()[0] for line in result.output.split("Commands:")[1].splitlines() if line.strip()]
    assert result.exit_code == 0 and listed == list(COMMAND_ORDER)
    code = "import sys, relightanyone.cli; print(sorted({'torch', 'cv2'} & set(sys.modules)))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert loaded.stdout.strip() == "[]"


def test_shared_option_choices_match_the_layers():
    from relightanyone.ingest.runner import PRESET_SIZES
    from relightanyone.model.networks.presets import PRESETS, STAGE2_PRESETS

    assert set(PRESET_NAMES) == set(PRESET_SIZES) == set(PRESETS) == set(STAGE2_PRESETS)


@pytest.mark.parametrize("command", ["ingest custom", "expand", "export-dataset"])
def test_comma_separated_names_reach_the_command_as_one_tuple(command):
    """``--subjects a,b --subjects c`` is read the same way by every command that takes names."""
    group = cli
    for name in command.split():
        group = group.commands[name] if isinstance(group, click.Group) else group
    option = next(p for p in group.params if p.name == "subjects")
    ctx = click.Context(group)
    assert option.process_value(ctx, ("a,b", " c ")) == ("a", "b", "c")
    assert option.process_value(ctx, ()) is None
