"""Build and load the toolkit's compiled C++ parts (the rasterizer kernel, the mesh-silhouette kernel).

Each kernel is compiled with the machine's C++ compiler on first use through ``torch.utils.cpp_extension``
into ``$RELIGHTANYONE_CACHE`` (default ``~/.cache/relightanyone``) ``/torch_extensions/<name>``, where the
name carries a hash of the sources, the flags and the torch version, so an edited source or a new torch
rebuilds and an unchanged one loads in milliseconds. A file lock makes the first build safe when several
processes (pytest-xdist or ingest workers) start at once. When a kernel cannot be built, :func:`load_extension`
warns, saying what the caller falls back to, and returns ``None``.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import warnings
from collections.abc import Sequence
from pathlib import Path


def cache_dir() -> Path:
    """Root of the build cache (``$RELIGHTANYONE_CACHE`` or ``~/.cache/relightanyone``)."""
    return Path(os.environ.get("RELIGHTANYONE_CACHE", Path.home() / ".cache" / "relightanyone"))


def extension_name(
    prefix: str, sources: Sequence[Path], cflags: Sequence[str], ldflags: Sequence[str]
) -> str:
    """``<prefix>_<16 hex digits>``: the module name keyed by the sources, the flags and the torch version."""
    import torch

    digest = hashlib.sha256()
    for source in sources:
        digest.update(Path(source).read_bytes())
    digest.update(" ".join([*cflags, *ldflags]).encode())
    digest.update(torch.__version__.encode())
    return f"{prefix}_{digest.hexdigest()[:16]}"


def load_extension(
    prefix: str,
    sources: Sequence[Path],
    cflags: Sequence[str],
    ldflags: Sequence[str],
    what: str,
    fallback: str,
):
    """The compiled module of ``sources``, built on first use; ``None`` (with a warning) if it cannot be.

    Args:
        prefix: module name prefix (:func:`extension_name`).
        what: the kernel in words, for the warning (``"rasterizer"``).
        fallback: what the caller does without it, for the warning (``"using the slower PyTorch path"``).
    """
    name = extension_name(prefix, sources, cflags, ldflags)
    build_dir = cache_dir() / "torch_extensions" / name
    try:
        build_dir.mkdir(parents=True, exist_ok=True)
        from torch.utils.cpp_extension import load

        with open(build_dir / "build.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # one process builds, the others wait and then load its result
            # torch's own build baton: a builder killed mid-build leaves it behind and every later load would
            # wait for it forever. Under our lock nobody else is building, so any baton here is stale.
            (build_dir / "lock").unlink(missing_ok=True)
            try:
                built = _import_built(name, build_dir / f"{name}.so")
                if built is not None:
                    return built
                return load(
                    name=name,
                    sources=[str(source) for source in sources],
                    extra_cflags=list(cflags),
                    extra_ldflags=list(ldflags),
                    build_directory=str(build_dir),
                    verbose=False,
                )
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
    # No compiler, no ninja, a read-only cache: fall back, but say why and what to do.
    except Exception as error:
        message = str(error).strip()
        warnings.warn(
            f"relightanyone: could not build the C++ {what} kernel in {build_dir} ({type(error).__name__}: "
            f"{message.splitlines()[-1] if message else error}); {fallback}. Install a C++ compiler with "
            "OpenMP (e.g. g++) and ninja to enable it.",
            RuntimeWarning,
            stacklevel=3,
        )
        return None


def _import_built(name: str, library: Path):
    """The module from an already built ``library``, or None (absent or unloadable: build it).

    The name carries the hash of sources, flags and torch version, so a library under it is never stale;
    loading it directly skips ninja's check, which rebuilds whenever another process' environment wrote
    a different-looking command line into the shared build files (minutes of compiling on a small machine).
    """
    import importlib.util

    import torch  # noqa: F401  (the module links against torch's libraries, which this loads)

    if not library.is_file():
        return None
    try:
        spec = importlib.util.spec_from_file_location(name, library)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except ImportError:
        return None
    return module
