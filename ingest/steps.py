"""Image steps every ingest adapter shares: projection, crop box, undistort+crop+resize, mesh mask.

Camera conventions follow DESIGN §3: OpenCV pinhole (x right, y down, z forward), the centre of pixel
``(u, v)`` is at ``(u, v)``; resizing by ``s`` gives ``f *= s, c = (c + 0.5) s - 0.5``; cropping at
``(x0, y0)`` gives ``c -= (x0, y0)``. Distortion coefficients are in OpenCV order
``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]])``. Everything is plain numpy: ``K (3, 3)``,
``w2c (4, 4)``, ``dist (D,)``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# Largest supersampling factor per axis used to area-average when downscaling (memory: out² · k² pixels).
MAX_SUPERSAMPLING = 16


def _as_K(K: Any) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite (3, 3) intrinsic matrix with positive focals, got {K.tolist()}")
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        # OpenCV's projection and undistortion ignore skew, so a skewed K would silently disagree.
        raise ValueError(f"K must have zero skew and last row [0, 0, 1], got {K.tolist()}")
    return K


def _as_w2c(w2c: Any) -> np.ndarray:
    w2c = np.asarray(w2c, dtype=np.float64)
    if w2c.shape == (3, 4):
        w2c = np.vstack([w2c, [0.0, 0.0, 0.0, 1.0]])
    if w2c.shape != (4, 4) or not np.all(np.isfinite(w2c)):
        raise ValueError(f"w2c must be a finite (4, 4) world-to-camera matrix, got shape {w2c.shape}")
    return w2c


def _as_dist(dist: Any) -> np.ndarray:
    if dist is None:
        return np.zeros(0)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if dist.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise ValueError(
            f"dist must hold 0, 4, 5, 8, 12 or 14 finite OpenCV coefficients, got {dist.tolist()}"
        )
    return dist


def _size_wh(size: Any) -> tuple[int, int]:
    if isinstance(size, (int, np.integer)):
        width = height = int(size)
    else:
        width, height = (int(v) for v in size)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive (width, height), got {size}")
    return width, height


def project_points(points: Any, K: Any, w2c: Any, dist: Any = None) -> np.ndarray:
    """Project world points to pixels.

    Args:
        points: ``(N, 3)`` world points (in front of the camera).
        K: ``(3, 3)`` intrinsics; w2c: ``(4, 4)`` world→camera; dist: ``(D,)`` OpenCV coefficients or None.
    Returns:
        ``(N, 2)`` float64 pixel coordinates (pixel centres at integers).
    """
    import cv2

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    K, w2c, dist = _as_K(K), _as_w2c(w2c), _as_dist(dist)
    if pts.shape[0] == 0:
        return np.zeros((0, 2))
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    pixels, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], K, dist if dist.size else None)
    return pixels.reshape(-1, 2)


def crop_box_around_points(pixels: Any, image_size: Any, margin: float = 0.1) -> tuple[int, int, int, int]:
    """Square integer crop box around projected points, padded by ``margin`` of its side on each side.

    The box is ``(x0, y0, x1, y1)``, half-open: it holds pixels ``x0 .. x1 - 1`` (so it spans
    ``[x0 - 0.5, x1 - 0.5]`` in pixel coordinates). Side ``= ceil(extent · (1 + 2 margin))`` with ``extent``
    the larger side of the points' bounding box; the box is centred on that bounding box, ``x0 =
    floor(centre - side / 2 + 0.5)``. It may extend past the image (the missing part is zero padding).

    Args:
        pixels: ``(N, 2)`` pixel coordinates (e.g. projected mesh vertices).
        image_size: ``(width, height)`` of the source image; the box must overlap it.
        margin: fraction of the points' extent added on each side.
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    px = px[np.all(np.isfinite(px), axis=1)]
    if px.shape[0] == 0:
        raise ValueError("no finite pixel coordinates to crop around (is the mesh behind the camera?)")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    width, height = _size_wh(image_size)
    lo, hi = px.min(axis=0), px.max(axis=0)
    extent = float(max(hi - lo))
    side = max(int(math.ceil(extent * (1.0 + 2.0 * margin) - 1e-9)), 1)
    centre = (lo + hi) / 2.0
    x0 = int(math.floor(centre[0] - side / 2.0 + 0.5))
    y0 = int(math.floor(centre[1] - side / 2.0 + 0.5))
    box = (x0, y0, x0 + side, y0 + side)
    if box[2] <= 0 or box[3] <= 0 or box[0] >= width or box[1] >= height:
        raise ValueError(f"crop box {box} does not overlap the {width}×{height} image")
    return box


def crop_resize_intrinsics(K: Any, box: Any, out_size: int) -> np.ndarray:
    """Intrinsics of the crop ``box`` of an undistorted image resized to ``out_size²``.

    Crop: ``c -= (x0, y0)``; resize by ``s = out_size / side``: ``f *= s``, ``c = (c + 0.5) s - 0.5``
    (the skew term scales like a focal). Returns ``(3, 3)`` float64.
    """
    K = _as_K(K)
    x0, y0, x1, y1 = (int(v) for v in box)
    side = x1 - x0
    if side <= 0 or y1 - y0 != side:
        raise ValueError(f"crop box must be a non-empty square (x0, y0, x1, y1), got {tuple(box)}")
    scale = out_size / side
    K_new = K.copy()
    K_new[0, 2] -= x0
    K_new[1, 2] -= y0
    K_new[:2, :2] *= scale
    K_new[:2, 2] = (K_new[:2, 2] + 0.5) * scale - 0.5
    return K_new


def _resample(image: np.ndarray, K: np.ndarray, dist: np.ndarray, K_out: np.ndarray, size: int) -> np.ndarray:
    """One remap from the distorted source into the pinhole camera ``K_out`` with a ``size²`` image."""
    import cv2

    map_x, map_y = cv2.initUndistortRectifyMap(
        K, dist if dist.size else None, np.eye(3), K_out, (size, size), cv2.CV_32FC1
    )
    return cv2.remap(
        image, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )


def undistort_crop_resize(
    image: np.ndarray, K: Any, dist: Any, box: Any, out_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Undistort, crop and resize in one resampling; returns the new image and its pinhole ``K``.

    The output is the view of the *undistorted* camera (same focal and centre, no distortion) cropped to
    ``box`` and scaled to ``out_size × out_size``; its intrinsics are :func:`crop_resize_intrinsics`.
    Pixels outside the source are 0.

    Anti-aliasing: when the output is ``k``× coarser than the source (``k = ceil(side / out_size)`` > 1,
    capped at :data:`MAX_SUPERSAMPLING`), the remap renders a ``k·out_size`` image (bilinear, spacing ≤ 1
    source pixel) and ``cv2.INTER_AREA`` averages each ``k×k`` block: a box filter over the output pixel's
    footprint. The supersampled camera is exactly ``K_new`` resized by ``k``, so geometry is unchanged.

    Args:
        image: ``(H, W)`` or ``(H, W, C)``; float32/float64 (linear colour) or uint8/uint16 (alpha maps).
        K: ``(3, 3)``; dist: ``(D,)`` OpenCV coefficients or None; box: square ``(x0, y0, x1, y1)``.
        out_size: output side in pixels.
    Returns:
        ``(out (out_size, out_size[, C]) same dtype, K_new (3, 3))``.
    """
    import cv2

    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {img.shape}")
    if img.dtype not in (np.float32, np.float64, np.uint8, np.uint16):
        raise ValueError(f"image dtype must be float32, float64, uint8 or uint16, got {img.dtype}")
    if int(out_size) <= 0:
        raise ValueError(f"out_size must be positive, got {out_size}")
    out_size = int(out_size)
    K, dist = _as_K(K), _as_dist(dist)
    K_new = crop_resize_intrinsics(K, box, out_size)
    side = int(box[2]) - int(box[0])
    factor = min(max(int(math.ceil(side / out_size - 1e-9)), 1), MAX_SUPERSAMPLING)
    # Integer images are resampled in float32 and rounded once, after the averaging.
    work = img if np.issubdtype(img.dtype, np.floating) else img.astype(np.float32)
    K_ss = crop_resize_intrinsics(K, box, out_size * factor)
    out = _resample(work, K, dist, K_ss, out_size * factor)
    if factor > 1:
        out = cv2.resize(out, (out_size, out_size), interpolation=cv2.INTER_AREA)
    if out.ndim == 2 and img.ndim == 3:
        out = out[:, :, None]  # OpenCV drops a single channel axis
    if np.issubdtype(img.dtype, np.integer):
        limit = np.iinfo(img.dtype).max
        out = np.clip(np.round(out), 0, limit).astype(img.dtype)
    else:
        out = out.astype(img.dtype, copy=False)
    return out, K_new


def _pixel_rays(
    K: np.ndarray, w2c: np.ndarray, window: tuple[int, int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origins and unit directions ``(h·w, 3)`` through the pixel centres of
    ``window = (x0, y0, x1, y1)`` (half-open), row-major."""
    x0, y0, x1, y1 = window
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    dirs_cam = pix @ np.linalg.inv(K).T
    R, t = w2c[:3, :3], w2c[:3, 3]
    dirs = dirs_cam @ R  # R^T applied to each row
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.broadcast_to(-R.T @ t, dirs.shape)
    return np.ascontiguousarray(origins), dirs


def mesh_mask(vertices: Any, faces: Any, neck_face_mask: Any, K: Any, w2c: Any, size: Any) -> np.ndarray:
    """Silhouette of a mesh seen by a pinhole camera, cut below the neck line.

    One ray per pixel centre (trimesh with the embree backend when installed); a pixel is in the mask when
    its first hit is a face not flagged in ``neck_face_mask``, so the neck and anything seen through it
    are excluded while the chin in front of the neck is kept.

    Args:
        vertices: ``(V, 3)`` canonical-space vertices; faces: ``(F, 3)`` int.
        neck_face_mask: ``(F,)`` bool, True for faces below the neck line; None keeps every face.
        K: ``(3, 3)`` intrinsics of the stored (undistorted) image; w2c: ``(4, 4)`` world→camera.
        size: ``(width, height)`` or an int for a square image.
    Returns:
        ``(H, W)`` bool.
    """
    import trimesh

    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3) and faces (F, 3), got {V.shape} and {F.shape}")
    if F.size and (F.min() < 0 or F.max() >= V.shape[0]):
        raise ValueError(f"faces index vertices outside 0..{V.shape[0] - 1}")
    if neck_face_mask is None:
        neck = np.zeros(F.shape[0], dtype=bool)
    else:
        neck = np.asarray(neck_face_mask, dtype=bool).reshape(-1)
        if neck.shape != (F.shape[0],):
            raise ValueError(f"neck_face_mask must be ({F.shape[0]},) bool, got {neck.shape}")
    width, height = _size_wh(size)
    K, w2c = _as_K(K), _as_w2c(w2c)
    window = _projected_window(V[np.unique(F)] if F.size else V[:0], K, w2c, width, height)
    mask = np.zeros((height, width), dtype=bool)
    if window is None:
        return mask
    mesh = trimesh.Trimesh(vertices=V, faces=F, process=False)
    origins, dirs = _pixel_rays(K, w2c, window)
    first = np.asarray(mesh.ray.intersects_first(ray_origins=origins, ray_directions=dirs))
    hit = first >= 0
    keep = np.zeros_like(hit)
    keep[hit] = ~neck[first[hit]]
    x0, y0, x1, y1 = window
    mask[y0:y1, x0:x1] = keep.reshape(y1 - y0, x1 - x0)
    return mask


def _projected_window(
    vertices: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int
) -> tuple[int, int, int, int] | None:
    """Pixel window ``(x0, y0, x1, y1)`` that can contain the mesh, or None when it is empty.

    A pinhole projection of a triangle lies inside the hull of its projected vertices, so when every
    vertex is in front of the camera only the (1 px padded) bounding box needs rays; otherwise the whole
    image is cast.
    """
    if vertices.shape[0] == 0:
        return None
    cam = vertices @ w2c[:3, :3].T + w2c[:3, 3]
    if np.any(cam[:, 2] <= 1e-9):
        return (0, 0, width, height)
    px = (cam / cam[:, 2:3]) @ K.T
    x0 = max(int(np.floor(px[:, 0].min())) - 1, 0)
    y0 = max(int(np.floor(px[:, 1].min())) - 1, 0)
    x1 = min(int(np.ceil(px[:, 0].max())) + 2, width)
    y1 = min(int(np.ceil(px[:, 1].max())) + 2, height)
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1, y1)
