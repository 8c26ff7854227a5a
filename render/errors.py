"""The input error of the render layer, shared with align (which imports render).

render imports no root module but ``relightanyone.compiled``, so this error cannot share the project's
base class (:mod:`relightanyone.errors`); the command line lists it by type instead.
"""

from __future__ import annotations


class FileFormatError(ValueError):
    """A file (mesh, environment map, colour calibration) cannot be read as what it should be; the message
    names the file and the problem."""
