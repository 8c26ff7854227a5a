"""The ``relightanyone`` command.

Each layer keeps its commands in its own ``cli.py`` as a ``COMMANDS`` mapping of name to a click
command; this module gathers them, lists them in data-flow order, and is the one error boundary of every
command. The layer modules import nothing heavy at module level (torch, OpenCV, ...): the commands
import those in their bodies, so that ``relightanyone --help`` stays instant.

The error boundary: an expected failure escaping a command (a project error, :mod:`relightanyone.errors`;
an input error of render, align or synth, which cannot share that base; an ``OSError`` such as a missing
file, a read-only folder or a full disk; a path argument naming nothing) is printed as one line on stderr
that names the file and the problem, and the command exits with status 1. Anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import click

from relightanyone import __version__
from relightanyone.errors import RelightAnyoneError
from relightanyone.os_errors import OUTPUT_META_KEY, os_error_line
from relightanyone.progress import PROGRESS_META_KEY, progress_bar
from relightanyone.render.errors import FileFormatError
from relightanyone.synth.errors import WorldError

LAYER_CLI_MODULES = (
    "relightanyone.synth.cli",
    "relightanyone.ingest.cli",
    "relightanyone.format.cli",
    "relightanyone.model.cli",
    "relightanyone.evaluation.cli",
    "relightanyone.pipelines.cli",
)
# The order of the help listing: the order in which data flows through the commands.
COMMAND_ORDER = (
    "synth",
    "synth-preview",
    "doctor",
    "ingest",
    "validate",
    "inspect",
    "export-dataset",
    "align-colour",
    "train",
    "render",
    "fit",
    "relight",
    "export",
    "plan",
    "expand",
    "evaluate",
    "report",
    "run",
)
# render, align and synth cannot import the project's base class (relightanyone.errors): their input errors
# are listed by type.
EXPECTED_FAILURES = (RelightAnyoneError, FileFormatError, WorldError, OSError)


def failure_line(error: BaseException, output: Path | str | None = None) -> str:
    """The one line an expected failure is reported as: for an OSError the path (its file, else ``output``,
    the folder the command writes), the problem and what to do (:func:`os_error_line`); otherwise the
    message, its lines joined by "; "."""
    text = os_error_line(error, output) if isinstance(error, OSError) else str(error) or type(error).__name__
    return "; ".join(line.strip() for line in text.splitlines() if line.strip())


class RelightAnyoneGroup(click.Group):
    """The top-level group: commands listed in the order they were added, one error boundary for all."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.commands)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except click.BadParameter as error:
            # A path argument that does not exist (or is a file, not a folder) is bad input, not misuse.
            if isinstance(getattr(error.param, "type", None), click.Path):
                raise click.ClickException(failure_line(error.format_message())) from None
            raise
        except EXPECTED_FAILURES as error:
            raise click.ClickException(failure_line(error, ctx.meta.get(OUTPUT_META_KEY))) from None


def _gather_commands() -> dict[str, click.Command]:
    """Every layer's commands, in ``COMMAND_ORDER``; a command defined twice or not placed is a bug."""
    commands: dict[str, click.Command] = {}
    for module_name in LAYER_CLI_MODULES:
        module = importlib.import_module(module_name)
        for name, command in module.COMMANDS.items():
            if name in commands:
                raise RuntimeError(f"command {name!r} is defined twice ({module_name})")
            commands[name] = command
    if set(commands) != set(COMMAND_ORDER):
        raise RuntimeError(
            f"COMMAND_ORDER lists {sorted(set(COMMAND_ORDER) - set(commands))} that no layer defines and "
            f"misses {sorted(set(commands) - set(COMMAND_ORDER))}"
        )
    return {name: commands[name] for name in COMMAND_ORDER}


@click.group(
    cls=RelightAnyoneGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110},
)
@click.version_option(__version__, prog_name="relightanyone")
def cli() -> None:
    """Relightable Gaussian head avatars from many multi-view capture datasets.

    Every stage of the pipeline is a sub-command listed below, in data-flow order; run
    `relightanyone COMMAND --help` for its options. Real downloads (or a synthetic world) are ingested
    into normalized datasets, checked, and used to train the model.
    """
    # Synth cannot import the project: its command takes the progress report from here.
    click.get_current_context().meta[PROGRESS_META_KEY] = progress_bar


for _name, _command in _gather_commands().items():
    cli.add_command(_command, _name)


def main() -> None:
    cli()
