"""Command-line options that several layers' commands share, declared once.

Every ``cli.py`` of a layer (synth excepted: it imports nothing of the project and keeps its own) builds
its options from these, so an option has one name, default and meaning everywhere. Only click is
imported here: the commands' modules are imported by ``relightanyone --help``, which must stay instant.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from relightanyone.os_errors import OUTPUT_META_KEY, check_writable
from relightanyone.parallel import EXECUTORS

# The size presets of ingest (crop size) and of the model (network size and schedule).
PRESET_NAMES = ("tiny", "demo", "small", "paper")
# Where the tasks of ingest and expand run: a local process pool, or a Ray cluster.

EXISTING_FOLDER = click.Path(exists=True, file_okay=False, path_type=Path)
EXISTING_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)
FOLDER = click.Path(file_okay=False, path_type=Path)
FILE = click.Path(dir_okay=False, path_type=Path)
ANY_PATH = click.Path(path_type=Path)

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]


def comma_separated(values: tuple[str, ...]) -> tuple[str, ...] | None:
    """``("a,b", "c")`` (a repeated option) -> ``("a", "b", "c")``; nothing given -> None (keep everything)."""
    names = tuple(name.strip() for value in values for name in value.split(",") if name.strip())
    return names or None


def parsed_by(parse: Callable[[Any], Any]) -> Callable[[click.Context, click.Parameter, Any], Any]:
    """A click callback that turns an option's raw value into ``parse(value)``; a ``ValueError`` from
    ``parse`` becomes a usage error that names the option. ``None`` (option not given) stays ``None``."""

    def callback(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        if value is None:
            return None
        try:
            return parse(value)
        except ValueError as error:
            raise click.BadParameter(str(error), ctx=ctx, param=param) from None

    return callback


def names_option(name: str, help: str, metavar: str = "A,B") -> Decorator:
    """A repeatable option of comma-separated names; the command gets a tuple, or None when not given."""
    return click.option(name, multiple=True, metavar=metavar, callback=parsed_by(comma_separated), help=help)


def out_option(help: str, *, file: bool = False, required: bool = True, dest: str | None = None) -> Decorator:
    """``--out``: the folder (or, with ``file``, the file) a command writes. It is probed while the command
    line is parsed (:func:`check_writable`), so a read-only or unwritable place stops the command before it
    plans anything, and it is recorded for the error boundary (an OS error that names no file)."""
    declarations = ("--out", dest) if dest else ("--out",)

    def writable(ctx: click.Context, param: click.Parameter, value: Path | None) -> Path | None:
        if value is not None and not ctx.resilient_parsing:
            ctx.meta[OUTPUT_META_KEY] = value
            check_writable(value.parent if file else value)
        return value

    return click.option(
        *declarations,
        type=FILE if file else FOLDER,
        required=required,
        default=None,
        callback=writable,
        help=help,
    )


def seed_option(help: str | None = None) -> Decorator:
    return click.option("--seed", type=int, default=0, show_default=True, help=help)


def threads_option() -> Decorator:
    return click.option(
        "--threads",
        type=int,
        default=None,
        help="CPU threads for torch (default: torch's choice; use 1 on a machine shared with other jobs).",
    )


def device_option() -> Decorator:
    return click.option(
        "--device",
        default="auto",
        show_default=True,
        help="Torch device: auto (CUDA when available, else CPU), cpu, cuda, cuda:1, ...",
    )


# Arithmetic of the convolutional map networks (mixed precision); everything else stays float32.
PRECISION_NAMES = ("fp32", "bf16")


def precision_option() -> Decorator:
    return click.option(
        "--precision",
        type=click.Choice(PRECISION_NAMES),
        default="fp32",
        show_default=True,
        help="fp32, or bf16: the convolutional map networks run under bfloat16 autocast (per-Gaussian "
        "maths, rasterization and losses stay float32).",
    )


def loader_workers_option() -> Decorator:
    return click.option(
        "--loader-workers",
        type=click.IntRange(min=0),
        default=None,
        help="Processes that make the next training batches during a step (default: 0 on the CPU, up to 4 "
        "with CUDA). Batches depend on the iteration alone, so the weights do not depend on this.",
    )


def quiet_option(help: str = "No progress bars.") -> Decorator:
    return click.option("--quiet", is_flag=True, help=help)


def dry_run_option(help: str) -> Decorator:
    return click.option("--dry-run", is_flag=True, help=help)


def preset_option(default: str, help: str) -> Decorator:
    return click.option(
        "--preset", type=click.Choice(PRESET_NAMES), default=default, show_default=True, help=help
    )


def workers_option(help: str | None = None) -> Decorator:
    return click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True, help=help)


def executor_option() -> Decorator:
    return click.option(
        "--executor",
        type=click.Choice(EXECUTORS),
        default="local",
        show_default=True,
        help="Task executor: a local process pool, or Ray (pip install 'relightanyone[ray]').",
    )


def fit_iterations_option(default: tuple[int, int], help: str) -> Decorator:
    """``--fit-iterations N M``: inversion and finetuning steps of a fit."""
    return click.option(
        "--fit-iterations",
        nargs=2,
        type=click.IntRange(min=0),
        default=default,
        show_default=True,
        metavar="N M",
        help=help,
    )


def options(*decorators: Decorator) -> Decorator:
    """Several option decorators as one, applied in the order listed (the order of ``--help``)."""

    def apply(function: Callable[..., Any]) -> Callable[..., Any]:
        for decorator in reversed(decorators):
            function = decorator(function)
        return function

    return apply
