"""relightanyone: relightable Gaussian head avatars from many multi-view capture datasets.

The top-level folders of the source tree are imported as ``relightanyone.<folder>``:
``render`` (cameras, rasterizer, shading), ``align`` (colour and geometry maths), ``ingest`` (one adapter
per native layout), ``model`` (stage 1, stage 2, fitting), ``evaluation`` (scores against the synthetic
world), ``pipelines`` (DAG runner, expansion, report) and ``synth`` (the ground-truth world); ``format``
(the normalized dataset) lives in this package. ``docs/architecture.md`` describes the layers.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("relightanyone")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

import warnings as _warnings

# colour-science announces at import that its optional plotting API needs Matplotlib; nothing here plots
# through it, so the notice is noise on every command.
_warnings.filterwarnings("ignore", message='"Matplotlib" related API features are not available')
