"""The ingest adapters: one module per native layout, all behind one contract.

An adapter module reads one native layout and describes what it finds as a
:class:`~relightanyone.ingest.records.DatasetPlan`; the shared runner does the rest. Every adapter
provides the same four things (:class:`Adapter`), and the ``ingest`` command is built from
:data:`ADAPTERS`, so adding a layout means adding a module and one line here.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

from relightanyone.ingest.records import AdapterOptions, DatasetPlan


@runtime_checkable
class Adapter(Protocol):
    """The contract of an adapter module.

    ``NAME`` is the default dataset name, ``KIND`` ``"olat"`` or ``"flat"``. ``detect(src)`` checks the
    layout cheaply and returns its version (raising :class:`~relightanyone.ingest.records.LayoutError`
    that names what is missing); ``plan(src, options)`` reads calibration, colour and file lists.
    """

    NAME: str
    KIND: str

    def detect(self, src: Path) -> str: ...

    def plan(self, src: Path, options: AdapterOptions) -> DatasetPlan: ...


@dataclass(frozen=True)
class AdapterSpec:
    """One registered adapter: its sub-command, its module and what its command asks for."""

    command: str
    module: str
    description: str
    tracking_required: bool = True


ADAPTERS: dict[str, AdapterSpec] = {
    spec.command: spec
    for spec in (
        AdapterSpec("faceolat", "faceolat", "FaceOLAT / 3DPR light-stage captures (OLAT and full-on frames)"),
        AdapterSpec("ava256", "ava256", "Ava-256 captures (flat-lit, AVIF frames in per-camera zips)"),
        AdapterSpec(
            "stereo-rig", "stereo_rig", "SDFM-style stereo rig (RAW DNG, COLMAP model, colour chart)"
        ),
        AdapterSpec("nersemble", "nersemble", "NeRSemble v1/v2 multi-view video captures"),
        AdapterSpec(
            "custom",
            "custom",
            "any rig with OpenCV cameras.json, images and tracked meshes",
            tracking_required=False,
        ),
    )
}


def load_adapter(command: str) -> Adapter:
    """Import the adapter registered as ``command``; a module that breaks the contract is a bug."""
    spec = ADAPTERS[command]
    module = importlib.import_module(f"relightanyone.ingest.{spec.module}")
    if not isinstance(module, Adapter):
        raise TypeError(f"relightanyone.ingest.{spec.module} does not provide NAME, KIND, detect and plan")
    return module
