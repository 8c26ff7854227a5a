"""The report's ``assets/`` folder: input pictures copied in, linear HDR images and arrays written as PNG.

Names are derived from the section, the order of the inputs and their titles, never from time or
absolute paths, so the same inputs give the same folder byte for byte. Browsers show PNG, JPEG, GIF,
WebP, AVIF, BMP and SVG as they are; ``.exr`` / ``.hdr`` pictures are scene-linear and are tone-mapped
to an sRGB PNG (99th percentile of the lit pixels at 0.9).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from relightanyone.errors import InputError
from relightanyone.format.preview import linear_to_srgb_preview
from relightanyone.pipelines.report.html import slug
from relightanyone.render.envmap import load_envmap

BROWSER_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif", ".webp", ".avif", ".bmp", ".svg")
HDR_SUFFIXES = (".exr", ".hdr")
IMAGE_SUFFIXES = BROWSER_IMAGE_SUFFIXES + HDR_SUFFIXES


class UnreadablePicture(InputError):
    """A picture file exists but cannot be decoded; the message names the file."""


def write_png(path: Path, image: np.ndarray) -> None:
    """Write (H, W, 3) or (H, W) uint8 as PNG with Pillow (deterministic: no time or text chunks)."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image)).save(path, format="PNG")


def hdr_to_srgb(path: Path) -> np.ndarray:
    """A lat-long or plain ``.exr`` / ``.hdr`` file -> (H, W, 3) uint8 sRGB preview."""

    try:
        linear = load_envmap(path).permute(1, 2, 0).numpy()
    except (OSError, ValueError, RuntimeError) as error:
        raise UnreadablePicture(f"{path}: cannot read the HDR image ({error})") from None
    return linear_to_srgb_preview(linear)


def check_browser_picture(path: Path) -> None:
    """Raise ``UnreadablePicture`` when Pillow cannot decode ``path`` (SVG is passed through unchecked)."""
    if path.suffix.lower() == ".svg":
        return
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as picture:
            picture.verify()
    except (OSError, UnidentifiedImageError, SyntaxError) as error:
        raise UnreadablePicture(f"{path}: not a readable image ({error})") from None


class AssetStore:
    """Files under ``<report>/assets/``; every method returns the URL relative to ``index.html``."""

    def __init__(self, report_dir: Path):
        self.report_dir = Path(report_dir)
        self.root = self.report_dir / "assets"
        self._used: set[str] = set()
        self._counts: dict[str, int] = {}

    def _name(self, section: str, title: str, suffix: str) -> str:
        folder = slug(section)
        number = self._counts.get(folder, 0)
        self._counts[folder] = number + 1
        url = f"assets/{folder}/{number:02d}-{slug(title)}{suffix}"
        if url in self._used:  # cannot happen with the counter, but never overwrite an asset
            raise RuntimeError(f"asset name clash: {url}")
        self._used.add(url)
        return url

    def add_picture(self, section: str, title: str, source: Path) -> str:
        """Copy a browser-ready picture, or tone-map an HDR one to PNG; raises ``UnreadablePicture``."""
        source = Path(source)
        suffix = source.suffix.lower()
        if suffix in HDR_SUFFIXES:
            image = hdr_to_srgb(source)
            url = self._name(section, title, ".png")
            write_png(self.report_dir / url, image)
            return url
        if suffix not in BROWSER_IMAGE_SUFFIXES:
            raise UnreadablePicture(
                f"{source}: '{suffix}' is not a picture format the report shows "
                f"(use one of {', '.join(IMAGE_SUFFIXES)})"
            )
        check_browser_picture(source)
        url = self._name(section, title, suffix)
        (self.report_dir / url).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, self.report_dir / url)
        return url

    def add_array(self, section: str, title: str, image: np.ndarray) -> str:
        """Write a generated (H, W, 3) uint8 sRGB picture as PNG."""
        url = self._name(section, title, ".png")
        write_png(self.report_dir / url, image)
        return url

    def add_file(self, section: str, relative: str, source: Path) -> str:
        """Copy any file keeping its relative path under ``assets/<section>/`` (for embedded documents)."""
        parts = [
            slug(p, limit=80) if p not in (".", "..") else "x" for p in Path(relative).with_suffix("").parts
        ]
        url = f"assets/{slug(section)}/{'/'.join(parts)}{Path(relative).suffix.lower()}"
        if url not in self._used:
            self._used.add(url)
            (self.report_dir / url).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, self.report_dir / url)
        return url
