"""Progress that fits where it goes: a live bar on a terminal, a plain line every few seconds in a log.

Every long loop of the toolkit reports through :func:`progress_bar`. On a terminal it is a tqdm bar. When
the stream is not a terminal (a pipeline stage's ``_stage.log``, a CI log, a pipe), redrawing a bar would
write a line per update, so it prints one plain line every ``LOG_INTERVAL_S`` seconds and one at the end
instead (``ingest demo: 120/480 view (25%), 31 s, 3.9 view/s``).

The object returned has the part of tqdm's interface the toolkit uses: iteration over the wrapped
iterable, ``update``, ``set_postfix``, ``set_description``, ``close`` and use as a context manager.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import IO, Any

from tqdm import tqdm

# Seconds between two progress lines in a log.
LOG_INTERVAL_S = 10.0
# Where the command line hands :func:`progress_bar` (in the click context's ``meta``) to the commands of
# layers that cannot import it (synth).
PROGRESS_META_KEY = "relightanyone.progress"


def monotonic() -> float:
    """The clock of progress reports, in seconds (a module function, so that a test can replace it)."""
    return time.monotonic()


def is_terminal(stream: IO[str]) -> bool:
    """Whether ``stream`` is an interactive terminal (where a bar can redraw itself in place)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class LogProgress:
    """A progress report for logs: a plain line every ``interval`` seconds of ``clock`` and one at the end.

    ``clock`` is a function returning seconds (:func:`monotonic`); tests pass their own.
    """

    def __init__(
        self,
        iterable: Iterable | None = None,
        *,
        total: int | None = None,
        desc: str = "",
        unit: str = "it",
        initial: int = 0,
        stream: IO[str],
        clock: Callable[[], float] = monotonic,
        interval: float = LOG_INTERVAL_S,
    ):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.iterable = iterable
        self.total = total
        self.desc = desc
        self.unit = unit
        self.n = initial
        self.initial = initial
        self.stream = stream
        self.clock = clock
        self.interval = interval
        self.postfix = ""
        self.started = clock()
        self.last_line = self.started
        self.closed = False

    def __iter__(self) -> Iterator:
        try:
            for item in self.iterable or ():
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> LogProgress:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        now = self.clock()
        if now - self.last_line >= self.interval:
            self._print(now)

    def set_postfix(self, values: dict[str, Any] | None = None, **more: Any) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in {**(values or {}), **more}.items())

    def set_description(self, desc: str) -> None:
        self.desc = desc

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._print(self.clock())

    def line(self, now: float) -> str:
        """The progress line at time ``now``: count, share of the total, seconds and rate."""
        elapsed = now - self.started
        done = f"{self.n}/{self.total}" if self.total else str(self.n)
        share = f" ({100 * self.n / self.total:.0f}%)" if self.total else ""
        rate = f", {(self.n - self.initial) / elapsed:.3g} {self.unit}/s" if elapsed > 0 else ""
        postfix = f", {self.postfix}" if self.postfix else ""
        return f"{self.desc}: {done} {self.unit}{share}, {elapsed:.0f} s{rate}{postfix}"

    def _print(self, now: float) -> None:
        self.last_line = now
        print(self.line(now), file=self.stream, flush=True)


class NoProgress(LogProgress):
    """A disabled report: iterates and counts, prints nothing."""

    def _print(self, now: float) -> None:
        pass


def progress_bar(
    iterable: Iterable | None = None,
    *,
    total: int | None = None,
    desc: str = "",
    unit: str = "it",
    initial: int = 0,
    disable: bool = False,
    stream: IO[str] | None = None,
    clock: Callable[[], float] | None = None,
):
    """A progress report over ``iterable`` (or of ``total`` steps advanced by ``update``) on ``stream``
    (default: standard error): a tqdm bar on a terminal, :class:`LogProgress` lines elsewhere, nothing
    when ``disable``. ``clock`` defaults to :func:`monotonic`."""
    stream = sys.stderr if stream is None else stream
    clock = monotonic if clock is None else clock
    options = {"total": total, "desc": desc, "unit": unit, "initial": initial}
    if disable:
        return NoProgress(iterable, stream=stream, clock=clock, **options)
    if is_terminal(stream):
        return tqdm(iterable, file=stream, dynamic_ncols=True, **options)
    return LogProgress(iterable, stream=stream, clock=clock, **options)
