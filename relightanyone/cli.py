"""The ``relightanyone`` command.

Each layer keeps its commands in its own ``cli.py`` as a ``COMMANDS`` mapping of name to a click
command; this module only gathers them, so ``--help`` lists exactly the stages that exist. The layer
modules import nothing heavy at module level (torch, OpenCV, ...) so that ``--help`` stays instant.
"""

from __future__ import annotations

import importlib

import click

from relightanyone import __version__

# Order is the order of the data flow; it is also the order of the help listing.
LAYER_CLI_MODULES = (
    "relightanyone.synth.cli",
    "relightanyone.ingest.cli",
    "relightanyone.format.cli",
    "relightanyone.model.cli",
    "relightanyone.evaluation.cli",
    "relightanyone.pipelines.cli",
)


class _OrderedGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.commands)


def _gather_commands() -> dict[str, click.Command]:
    commands: dict[str, click.Command] = {}
    for module_name in LAYER_CLI_MODULES:
        module = importlib.import_module(module_name)
        for name, command in module.COMMANDS.items():
            if name in commands:
                raise RuntimeError(f"command {name!r} is defined twice ({module_name})")
            commands[name] = command
    return commands


@click.group(
    cls=_OrderedGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110},
)
@click.version_option(__version__, prog_name="relightanyone")
def cli() -> None:
    """Relightable Gaussian head avatars from many multi-view capture datasets.

    Every stage of the pipeline is a sub-command listed below, in data-flow order; run
    `relightanyone COMMAND --help` for its options. Real downloads (or a synthetic world) are ingested
    into normalized datasets, checked, and used to train the model.
    """


for _name, _command in _gather_commands().items():
    cli.add_command(_command, _name)


def main() -> None:
    cli()
