"""Pictures of a dataset: sRGB previews of linear images and a contact sheet with mask outlines."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from relightanyone.align.colour import linear_to_display

LABEL_HEIGHT = 18
OUTLINE_RGB = (255, 64, 32)


def linear_to_srgb_preview(image: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """(H, W, 3) linear float -> (H, W, 3) uint8 sRGB (:func:`~relightanyone.align.colour.linear_to_display`).
    ``exposure`` multiplies the linear values; ``None`` maps the 99th percentile of the non-black pixels to 0.9
    so dim captures stay visible."""
    image = np.asarray(image, dtype=np.float32)
    if exposure is None:
        lit = image[image.max(axis=-1) > 1e-4]
        reference = float(np.percentile(lit, 99)) if lit.size else 1.0
        exposure = 0.9 / reference if reference > 0 else 1.0
    return linear_to_display(image, exposure)


def _fit_tile(image: np.ndarray, tile: int) -> tuple[np.ndarray, float]:
    import cv2

    scale = tile / max(image.shape[:2])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR), scale


def render_contact_sheet(
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    labels: Sequence[str],
    tile: int = 256,
    columns: int | None = None,
) -> np.ndarray:
    """A grid of previews with mask outlines and a label under each tile.

    images: N arrays (H_i, W_i, 3), linear float (sRGB-encoded for display) or already uint8 sRGB.
    masks: N arrays (H_i, W_i) in [0, 1] (or ``None`` for no outline). labels: N strings.
    Returns (rows * (tile + LABEL_HEIGHT), columns * tile, 3) uint8 sRGB.
    """
    import cv2

    if not (len(images) == len(masks) == len(labels)) or not images:
        raise ValueError(
            f"need as many images, masks and labels (>0); got {len(images)}, {len(masks)}, {len(labels)}"
        )
    columns = columns or int(np.ceil(np.sqrt(len(images))))
    rows = int(np.ceil(len(images) / columns))
    sheet = np.zeros((rows * (tile + LABEL_HEIGHT), columns * tile, 3), dtype=np.uint8)
    for n, (image, mask, label) in enumerate(zip(images, masks, labels, strict=True)):
        preview = image if image.dtype == np.uint8 else linear_to_srgb_preview(image)
        preview, _ = _fit_tile(np.ascontiguousarray(preview), tile)
        if mask is not None:
            small = cv2.resize(
                (np.asarray(mask) >= 0.5).astype(np.uint8),
                preview.shape[1::-1],
                interpolation=cv2.INTER_NEAREST,
            )
            contours, _ = cv2.findContours(small, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            preview = np.ascontiguousarray(preview)
            cv2.drawContours(preview, contours, -1, OUTLINE_RGB, 1)
        top, left = (n // columns) * (tile + LABEL_HEIGHT), (n % columns) * tile
        sheet[top : top + preview.shape[0], left : left + preview.shape[1]] = preview
        cv2.putText(
            sheet,
            label[:40],
            (left + 3, top + tile + LABEL_HEIGHT - 5),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.33,
            (230, 230, 230),
            1,
            cv2.LINE_AA,
        )
    return sheet
