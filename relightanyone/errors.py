"""The project's expected failures: problems with what a user gave, not bugs.

Every layer that may import root modules raises these (or its own subclasses: ``LayoutError``,
``CalibrationError``, ``SchemaError``, ``IncompleteDatasetError``, ``PipelineError``, ...) for input
that cannot be used, with a message that names the file or folder and what is wrong with it. The
command line (:mod:`relightanyone.cli`) prints such a failure as one line on stderr and exits with
status 1; any other exception escaping a command is a bug and keeps its traceback.

render and align import no root module but :mod:`relightanyone.compiled`, and synth none at all; their
input errors subclass ``ValueError`` (:class:`relightanyone.render.errors.FileFormatError`,
:class:`relightanyone.synth.errors.WorldError`) and the command line lists them by type.
"""

from __future__ import annotations


class RelightAnyoneError(Exception):
    """An expected failure; the message names the file or folder and the problem."""


class InputError(RelightAnyoneError, ValueError):
    """A file, folder, run or option value is not what the step needs.

    Also a ``ValueError``, so code that handles bad values by catching ``ValueError`` keeps doing so.
    """


class DependencyError(RelightAnyoneError, RuntimeError):
    """An optional package or program the step needs (Ray, Chromium, ...) is not installed; the message says
    how to install it."""
