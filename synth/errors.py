"""The input error of the synthetic world.

synth imports nothing of the rest of the project, so this error cannot share the project's base class
(``relightanyone.errors``); the command line lists it by type instead.
"""

from __future__ import annotations


class WorldError(ValueError):
    """A world cannot be written or read where asked (a folder in use, no decodable images); the message
    names the folder and the problem."""
