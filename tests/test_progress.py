"""Progress fits where it goes: a bar on a terminal, a bounded number of plain lines in a log."""

from __future__ import annotations

import io
import re

from click.testing import CliRunner
from tqdm import tqdm

from relightanyone import progress
from relightanyone.cli import cli
from relightanyone.format.examples import write_example_dataset
from relightanyone.progress import LOG_INTERVAL_S, LogProgress, NoProgress, progress_bar


class FakeClock:
    """Seconds that advance by ``step`` on every reading."""

    def __init__(self, step: float):
        self.step = step
        self.now = 0.0

    def __call__(self) -> float:
        self.now += self.step
        return self.now


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_gets_a_line_every_interval_and_one_at_the_end():
    stream = io.StringIO()
    bar = progress_bar(total=200, desc="ingest demo", unit="view", stream=stream, clock=FakeClock(0.5))
    assert isinstance(bar, LogProgress)
    for _ in range(200):
        bar.update(1)
        bar.set_postfix({"loss": "0.5"})
    bar.close()
    bar.close()  # closing twice prints the final line once
    lines = stream.getvalue().splitlines()
    # 100 s of work at one line per interval, and the final line.
    assert len(lines) == 100 / LOG_INTERVAL_S + 1 and "\r" not in stream.getvalue()
    assert lines[0] == "ingest demo: 20/200 view (10%), 10 s, 2 view/s, loss=0.5"
    assert re.fullmatch(r"ingest demo: 200/200 view \(100%\), 100 s, 1.99 view/s, loss=0.5", lines[-1])


def test_a_terminal_gets_a_bar_and_disabled_prints_nothing():
    bar = progress_bar(range(3), desc="x", stream=Terminal())
    assert isinstance(bar, tqdm) and list(bar) == [0, 1, 2]
    stream = io.StringIO()
    quiet = progress_bar(range(3), desc="x", disable=True, stream=stream)
    assert isinstance(quiet, NoProgress) and list(quiet) == [0, 1, 2] and stream.getvalue() == ""


def test_iterating_counts_and_ends_with_one_line():
    stream = io.StringIO()
    assert list(progress_bar(["a", "b"], desc="export", unit="image", stream=stream, clock=FakeClock(0))) == [
        "a",
        "b",
    ]
    assert stream.getvalue() == "export: 2/2 image (100%), 0 s\n"


def test_a_command_writing_to_a_file_prints_a_bounded_number_of_lines(tmp_path, monkeypatch):
    dataset = write_example_dataset(tmp_path, subjects=tuple(f"s{i:03d}" for i in range(25)))  # 100 rows
    monkeypatch.setattr(progress, "monotonic", FakeClock(1.0))  # one second per row
    result = CliRunner().invoke(cli, ["validate", str(dataset), "--no-decode"])
    assert result.exit_code == 0, result.output
    assert "\r" not in result.output
    lines = result.output.splitlines()
    report = [line for line in lines if line.startswith("validate demo: ")]
    assert len(report) <= 100 / LOG_INTERVAL_S + 2 and report[-1].startswith(
        "validate demo: 100/100 row (100%)"
    )
    assert len(lines) == len(report) + 1 and lines[-1] == f"{dataset}: OK"


def test_synth_which_cannot_import_the_helper_reports_through_it_on_the_command_line(tmp_path):
    result = CliRunner().invoke(
        cli, ["synth", "--preset", "tiny", "--datasets", "d3", "--workers", "1", "--out", str(tmp_path / "w")]
    )
    assert result.exit_code == 0, result.output
    assert "\r" not in result.output
    assert re.search(r"^synth tiny d3: (\d+)/\1 render \(100%\)", result.output, re.MULTILINE)
