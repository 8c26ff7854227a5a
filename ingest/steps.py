"""Image steps every ingest adapter shares: projection, crop box, undistort+crop+resize, mesh mask.

Camera conventions (``docs/conventions.md``): OpenCV pinhole (x right, y down, z forward), the centre of pixel
``(u, v)`` is at ``(u, v)``; crops and resizes change K by ``render.camera.crop_intrinsics`` and
``resize_intrinsics``. Distortion coefficients are in OpenCV order
``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]])``. Everything is plain numpy: ``K (3, 3)``,
``w2c (4, 4)``, ``dist (D,)``.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np

from relightanyone.align.geometry import camera_centre
from relightanyone.compiled import load_extension
from relightanyone.format.schema import PADDING_WEIGHT_TOLERANCE
from relightanyone.render.camera import crop_intrinsics, resize_intrinsics

# Largest ratio of the remapped crop's side to the output's when downscaling (memory: out² · k² pixels).
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


# Points closer to the camera plane than this (camera z, in the points' units) count as behind it.
NEAR_PLANE = 1e-9


def _camera_points(points: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """``(N, 3)`` world points in camera coordinates."""
    return points @ w2c[:3, :3].T + w2c[:3, 3]


def _pinhole_pixels(camera_points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``(N, 2)`` pixels of ``(N, 3)`` camera-space points in front of a zero-skew pinhole ``K``."""
    return camera_points[:, :2] / camera_points[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]


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
    if not dist.any():  # plain pinhole: a few array operations, much cheaper than cv2.projectPoints
        return _pinhole_pixels(_camera_points(pts, w2c), K)
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
    if not np.isfinite(px).all():
        finite = np.isfinite(px)
        px = px[finite[:, 0] & finite[:, 1]]
    if px.shape[0] == 0:
        raise ValueError("no finite pixel coordinates to crop around (is the mesh behind the camera?)")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    width, height = _size_wh(image_size)
    # Per column: a reduction down the short axis of an (N, 2) array is several times slower.
    lo = np.array([px[:, 0].min(), px[:, 1].min()])
    hi = np.array([px[:, 0].max(), px[:, 1].max()])
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
    """Intrinsics of the crop ``box`` of an undistorted image resized to ``out_size²``: the crop at
    ``(x0, y0)``, then the resize by ``out_size / side``. Returns ``(3, 3)`` float64.
    """
    K = _as_K(K)
    x0, y0, x1, y1 = (int(v) for v in box)
    side = x1 - x0
    if side <= 0 or y1 - y0 != side:
        raise ValueError(f"crop box must be a non-empty square (x0, y0, x1, y1), got {tuple(box)}")
    scale = out_size / side
    return resize_intrinsics(crop_intrinsics(K, x0, y0), scale, scale)


def _resample(
    image: np.ndarray, K: np.ndarray, dist: np.ndarray, K_out: np.ndarray, size: int, with_taps: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """One remap of ``image`` from the distorted source into the pinhole camera ``K_out`` with a ``size²``
    image; with ``with_taps``, also ``(size, size)`` float32: 1 where every bilinear tap with a weight
    lies inside the source (see :func:`_taps_inside`), else 0."""
    import cv2

    map_x, map_y = cv2.initUndistortRectifyMap(
        K, dist if dist.size else None, np.eye(3), K_out, (size, size), cv2.CV_32FC1
    )
    out = cv2.remap(
        image, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    if not with_taps:
        return out, None
    height, width = image.shape[:2]
    return out, _taps_inside(map_x, map_y, width, height)


def _taps_inside(map_x: np.ndarray, map_y: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(h, w)`` float32, 1 where a bilinear remap of a ``width × height`` source at ``(map_x, map_y)``
    draws only on source pixels, else 0: what the same remap of an all-ones source gives exactly 1, without
    the remap. OpenCV rounds each coordinate to 1/32 of a pixel (``X = round(32 x)``, half to even) and
    reads the taps ``X // 32`` and ``X // 32 + 1``, the second with weight ``(X % 32) / 32``; so the taps
    with a weight are inside exactly when ``0 <= X <= 32 (width - 1)``, that is when
    ``-1/64 <= x <= width - 1 + 1/64`` (both ends round to the inside)."""
    import cv2

    margin = 1.0 / 64.0
    inside_x = cv2.inRange(map_x, -margin, width - 1 + margin)
    inside_y = cv2.inRange(map_y, -margin, height - 1 + margin)
    return (cv2.bitwise_and(inside_x, inside_y) & 1).astype(np.float32)


def _shifted_crop(image: np.ndarray, box: Any) -> np.ndarray:
    """The pixels of the square ``box`` ``(x0, y0, x1, y1)`` of ``image (H, W[, C])``, zero where the box
    leaves the image: what a pinhole remap by the integer shift ``(x0, y0)`` gives, without the map."""
    x0, y0, x1, y1 = (int(v) for v in box)
    height, width = image.shape[:2]
    out = np.zeros((y1 - y0, x1 - x0, *image.shape[2:]), dtype=image.dtype)
    sx0, sy0, sx1, sy1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = image[sy0:sy1, sx0:sx1]
    return out


def undistort_crop_resize(
    image: np.ndarray, K: Any, dist: Any, box: Any, out_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Undistort, crop and resize in one resampling; returns the new image and its pinhole ``K``.

    The output is the view of the *undistorted* camera (same focal and centre, no distortion) cropped to
    ``box`` and scaled to ``out_size × out_size``; its intrinsics are :func:`crop_resize_intrinsics`.
    Pixels outside the source are 0.

    Anti-aliasing: when the output is coarser than the source (``side > out_size``), the remap renders the
    crop at the source's own resolution (``side²``, capped at ``MAX_SUPERSAMPLING · out_size``; bilinear,
    one sample per source pixel) and ``cv2.INTER_AREA`` resizes it to ``out_size²``: an exact box filter
    over each output pixel's footprint. Resizing follows the same half-pixel rule as
    :func:`crop_resize_intrinsics`, so geometry is unchanged. A camera without distortion needs no remap
    at all: its undistorted crop is the source's pixels shifted by the box, so they are sliced (zero
    outside the image), the same values a remap would give, without building a map.

    Args:
        image: ``(H, W)`` or ``(H, W, C)``; float32/float64 (linear colour) or uint8/uint16 (alpha maps).
        K: ``(3, 3)``; dist: ``(D,)`` OpenCV coefficients or None; box: square ``(x0, y0, x1, y1)``.
        out_size: output side in pixels.
    Returns:
        ``(out (out_size, out_size[, C]) same dtype, K_new (3, 3))``.
    """
    out, K_new, _ = _undistort_crop_resize(image, K, dist, box, out_size, with_valid=False)
    return out, K_new


def undistort_crop_resize_valid(
    image: np.ndarray, K: Any, dist: Any, box: Any, out_size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`undistort_crop_resize` and the output's valid pixels, ``(out_size, out_size)`` bool: those
    whose value comes from the source alone, less than ``PADDING_WEIGHT_TOLERANCE`` of their resampling
    weight on the zero padding past the source's edge.

    Exact for every path of the resampler: a pixel is valid where an all-ones source, through the same
    remap (the same map) and the same area resize, gives 1. The remap's part is read off the map itself
    (:func:`_taps_inside`) instead of remapping a second image. A crop at least one pixel inside the
    image of a camera without distortion (every bilinear tap inside) is all valid at once.
    """
    return _undistort_crop_resize(image, K, dist, box, out_size, with_valid=True)


def _undistort_crop_resize(
    image: np.ndarray, K: Any, dist: Any, box: Any, out_size: int, with_valid: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Both of the above: ``(out, K_new, valid or None)``."""
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
    x0, y0, x1, y1 = (int(v) for v in box)
    side = x1 - x0
    height, width = img.shape[:2]
    inside = not dist.any() and x0 >= 1 and y0 >= 1 and x1 <= width - 1 and y1 <= height - 1
    coverage = with_valid and not inside
    covered = None  # (out_size, out_size) float32: each output pixel's weight on the source
    # Integer images are resampled in float32 and rounded once, after the averaging.
    work = img if np.issubdtype(img.dtype, np.floating) else img.astype(np.float32)
    if side > out_size:
        fine = min(side, out_size * MAX_SUPERSAMPLING)
        if fine == side and not dist.any():
            out = cv2.resize(_shifted_crop(work, box), (out_size, out_size), interpolation=cv2.INTER_AREA)
            if coverage:
                covered = _sliced_coverage(box, width, height, out_size)
        else:
            out, taps = _resample(work, K, dist, crop_resize_intrinsics(K, box, fine), fine, coverage)
            out = cv2.resize(out, (out_size, out_size), interpolation=cv2.INTER_AREA)
            if coverage:
                covered = cv2.resize(taps, (out_size, out_size), interpolation=cv2.INTER_AREA)
    else:
        out, covered = _resample(work, K, dist, K_new, out_size, coverage)
    if out.ndim == 2 and img.ndim == 3:
        out = out[:, :, None]  # OpenCV drops a single channel axis
    if np.issubdtype(img.dtype, np.integer):
        limit = np.iinfo(img.dtype).max
        out = np.clip(np.round(out), 0, limit).astype(img.dtype)
    else:
        out = out.astype(img.dtype, copy=False)
    if not with_valid:
        return out, K_new, None
    if covered is None:
        return out, K_new, np.ones((out_size, out_size), dtype=bool)
    return out, K_new, covered >= 1.0 - PADDING_WEIGHT_TOLERANCE


def _sliced_coverage(box: Any, width: int, height: int, out_size: int) -> np.ndarray:
    """``(out_size, out_size)`` float32: each output pixel's weight on the ``width × height`` source when
    the square ``box`` is sliced and area-resized. The area filter's weights are products of a weight
    along x and one along y, so two 1-D area resizes of the box's in-image indicator give it exactly."""
    import cv2

    x0, y0, x1, _ = (int(v) for v in box)
    side = x1 - x0
    per_axis = []
    for start, limit in ((x0, width), (y0, height)):
        pixels = np.arange(start, start + side)
        indicator = ((pixels >= 0) & (pixels < limit)).astype(np.float32)[None]
        per_axis.append(cv2.resize(indicator, (out_size, 1), interpolation=cv2.INTER_AREA)[0])
    along_x, along_y = per_axis
    return along_y[:, None] * along_x[None, :]


def _pixel_rays(
    K: np.ndarray, w2c: np.ndarray, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origins and directions ``(N, 3)`` through the pixel centres ``(u, v)`` (each
    ``(N,)``); directions are not normalised (the ray caster does that)."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    K_inv = np.linalg.inv(K)
    pix = np.stack([u, v, np.ones(u.size)], axis=1)
    dirs = pix @ (R.T @ K_inv).T  # camera rays K⁻¹ [u v 1]ᵀ turned into the world by Rᵀ
    return np.broadcast_to(-R.T @ t, dirs.shape), dirs


# Side in pixels of the blocks a silhouette is decided in: one ray per block away from the contours.
SILHOUETTE_BLOCK = 4
# Up to this many candidate pixels every one is cast: finding the contour blocks costs about 1.5 ms,
# more than it saves on small crops (measured: 128² crops, 2.5 ms direct; 1024², 124 ms vs 39 ms).
DIRECT_CAST_PIXELS = 16384
SILHOUETTE_SOURCES = [Path(__file__).resolve().parent / "csrc" / "mesh_silhouette.cpp"]
SILHOUETTE_CFLAGS = ["-O3", "-march=native", "-std=c++17"]
SILHOUETTE_METHODS = ("auto", "depth-buffer", "rays")


@functools.lru_cache(maxsize=1)
def load_silhouette_kernel():
    """The compiled depth-buffer silhouette (``ingest/csrc/mesh_silhouette.cpp``), or None (with a warning)
    when it cannot be built."""

    return load_extension(
        "relightanyone_silhouette",
        SILHOUETTE_SOURCES,
        SILHOUETTE_CFLAGS,
        [],
        "mesh-silhouette",
        "masks are cast one ray per pixel instead (same masks, several times slower)",
    )


class MeshSilhouette:
    """Silhouette of one mesh, cut below the neck line, seen by any pinhole camera.

    The rule is one ray per pixel centre: a pixel is in when the first face its ray hits is not flagged in
    ``neck_faces``, so the neck and anything seen through it are excluded while the chin in front of the
    neck is kept. Two ways to evaluate it, with the same answer:

    * ``"depth-buffer"`` (the compiled kernel): every face is drawn over the pixel centres inside its
      projection, nearest depth wins. For faces in front of a pinhole camera this is the ray rule exactly,
      and 3-4x faster than the rays below (``mask_methods`` in ``bench/results/ingest.json``). It needs
      every vertex in front of the camera.
    * ``"rays"`` (trimesh, with the embree backend when installed), with far fewer rays than pixels: only
      pixels inside the convex hull of the projected head (non-neck) vertices can be in; the answer changes
      from one pixel to the next only across the projection of a *contour edge* (a silhouette edge, whose
      two faces face opposite ways from the camera, a boundary or non-manifold edge, or an edge on the neck
      line), so blocks of ``SILHOUETTE_BLOCK``² pixels that no contour edge crosses take the answer of one
      ray, and the others cast every pixel (crops with more than ``DIRECT_CAST_PIXELS`` candidates; smaller
      ones cast every candidate). The ray structure and edge adjacency are built once per mesh.

    ``"auto"`` uses the depth buffer when the kernel is available and the mesh is in front of the camera,
    rays otherwise.

    Args:
        vertices: ``(V, 3)`` canonical-space vertices; faces: ``(F, 3)`` int.
        neck_faces: ``(F,)`` bool, True for faces below the neck line; None keeps every face.
        method: ``"auto"``, ``"depth-buffer"`` (an error where it cannot apply) or ``"rays"``.
    """

    def __init__(self, vertices: Any, faces: Any, neck_faces: Any = None, method: str = "auto"):
        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(faces, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3) and faces (F, 3), got {V.shape} and {F.shape}")
        if F.size and (F.min() < 0 or F.max() >= V.shape[0]):
            raise ValueError(f"faces index vertices outside 0..{V.shape[0] - 1}")
        if method not in SILHOUETTE_METHODS:
            raise ValueError(f"method must be one of {', '.join(SILHOUETTE_METHODS)}, got {method!r}")
        if neck_faces is None:
            neck = np.zeros(F.shape[0], dtype=bool)
        else:
            neck = np.asarray(neck_faces, dtype=bool).reshape(-1)
            if neck.shape != (F.shape[0],):
                raise ValueError(f"neck_face_mask must be ({F.shape[0]},) bool, got {neck.shape}")
        self.vertices, self.faces, self.neck_faces, self.method = V, np.ascontiguousarray(F), neck, method
        self.head_vertices = V[np.unique(F[~neck])] if F.size else V[:0]
        self._neck_flags = neck.astype(np.uint8)
        self._rays_ready = False
        self._ray_mesh = None

    def mask(self, K: Any, w2c: Any, size: Any) -> np.ndarray:
        """``(H, W)`` bool silhouette seen by ``K (3, 3)``, ``w2c (4, 4)``; size ``(width, height)`` or int."""
        K, w2c = _as_K(K), _as_w2c(w2c)
        width, height = _size_wh(size)
        if self.method != "rays":
            kernel = load_silhouette_kernel()
            cam = _camera_points(self.vertices, w2c)
            in_front = bool(np.all(cam[:, 2] > NEAR_PLANE))
            if kernel is not None and in_front:
                flags = kernel.first_hit_mask(
                    cam, self.faces, self._neck_flags, K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height
                )
                return flags.view(bool)
            if self.method == "depth-buffer":
                why = (
                    "kernel could not be built"
                    if kernel is None
                    else "needs every vertex in front of the camera"
                )
                raise ValueError(f"the depth-buffer silhouette {why}")
        return self._ray_mask(K, w2c, width, height)

    def _prepare_rays(self) -> None:
        """Face normals and contour-edge adjacency for the ray path, built on its first use."""
        F = self.faces
        corners = self.vertices[F] if F.size else np.zeros((0, 3, 3))
        self._face_points = corners[:, 0]
        self._face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        self._pair_edges, self._pair_faces, self._fixed_edges = _edge_adjacency(F, self.neck_faces)
        self._rays_ready = True

    def _ray_mask(self, K: np.ndarray, w2c: np.ndarray, width: int, height: int) -> np.ndarray:
        """The ray path of :meth:`mask`: ``(H, W)`` bool."""
        import cv2

        if not self._rays_ready:
            self._prepare_rays()
        region = _candidate_region(self.head_vertices, K, w2c, width, height)  # (H, W) uint8, 0 or 1
        candidates = np.flatnonzero(region)
        dirty = None
        if candidates.size > DIRECT_CAST_PIXELS:
            dirty = self._contour_blocks(K, w2c, width, height)  # None: the mesh reaches behind the camera
        mask = np.zeros(height * width, dtype=bool)
        if dirty is None:
            mask[candidates] = self._cast(K, w2c, candidates, width)
            return mask.reshape(height, width)
        block = SILHOUETTE_BLOCK
        rows, columns = dirty.shape
        padded = np.ones((rows * block, columns * block), dtype=np.uint8)  # pixels past the edge do not exist
        padded[:height, :width] = region
        # Area-averaging 0/1 pixels leaves 1 exactly where a whole block is a candidate.
        inside = cv2.resize(padded * 255, (columns, rows), interpolation=cv2.INTER_AREA) == 255
        # A clean block partly outside the hull is all out; one fully inside takes its corner pixel's ray.
        by, bx = np.nonzero(~dirty & inside)
        block_in = np.zeros((rows, columns), dtype=np.uint8)
        block_in[by, bx] = self._cast(K, w2c, (by * block) * width + bx * block, width)
        blocks = np.where(dirty, 2, block_in).astype(np.uint8)  # 0 out, 1 in, 2 cast every pixel
        per_pixel = cv2.resize(blocks, (columns * block, rows * block), interpolation=cv2.INTER_NEAREST)
        per_pixel = per_pixel[:height, :width].reshape(-1)
        mask[:] = per_pixel == 1
        cast = np.flatnonzero((per_pixel == 2) & (region.reshape(-1) > 0))
        mask[cast] = self._cast(K, w2c, cast, width)
        return mask.reshape(height, width)

    def _cast(self, K: np.ndarray, w2c: np.ndarray, pixels: np.ndarray, width: int) -> np.ndarray:
        """``(N,)`` bool: the rule for the flat pixel indices ``pixels (N,)``."""
        import trimesh

        if pixels.size == 0:
            return np.zeros(0, dtype=bool)
        if self._ray_mesh is None:
            self._ray_mesh = trimesh.Trimesh(vertices=self.vertices, faces=self.faces, process=False)
        v, u = np.divmod(pixels, width)
        origins, dirs = _pixel_rays(K, w2c, u.astype(np.float64), v.astype(np.float64))
        first = np.asarray(self._ray_mesh.ray.intersects_first(ray_origins=origins, ray_directions=dirs))
        keep = first >= 0
        keep[keep] = ~self.neck_faces[first[keep]]
        return keep

    def _contour_blocks(self, K: np.ndarray, w2c: np.ndarray, width: int, height: int) -> np.ndarray | None:
        """``(ceil(H / b), ceil(W / b))`` bool: blocks a projected contour edge may cross (grown by one
        block, so the line drawing cannot miss one); None when a vertex is not in front of the camera."""
        import cv2

        cam = _camera_points(self.vertices, w2c)
        if np.any(cam[:, 2] <= NEAR_PLANE):
            return None
        centre = camera_centre(w2c)
        facing = np.einsum("fi,fi->f", self._face_normals, centre - self._face_points) > 0
        turning = facing[self._pair_faces[:, 0]] != facing[self._pair_faces[:, 1]]
        edges = np.concatenate([self._fixed_edges, self._pair_edges[turning]])
        block, pad = SILHOUETTE_BLOCK, 2
        rows, columns = -(-height // block), -(-width // block)
        # Drawn with a margin: OpenCV's clipping of a segment that leaves the canvas can drop its last
        # cells, which must not be cells of the image.
        dirty = np.zeros((rows + 2 * pad, columns + 2 * pad), dtype=np.uint8)
        if edges.size:
            px = _pinhole_pixels(cam, K)
            if np.abs(px[edges]).max() > 1e6:  # beyond the fixed-point range of the drawing
                return np.ones((rows, columns), dtype=bool)
            # Block (i, j) holds pixels [j b, j b + b) × [i b, i b + b); its centre is at block coordinate j.
            segments = np.round(((px[edges] + 0.5) / block - 0.5 + pad) * 16).astype(np.int32)
            cv2.polylines(dirty, segments, isClosed=False, color=1, thickness=1, lineType=cv2.LINE_8, shift=4)
            dirty = cv2.dilate(dirty, np.ones((3, 3), np.uint8))
        return dirty[pad : pad + rows, pad : pad + columns].astype(bool)


def _edge_adjacency(faces: np.ndarray, neck: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges of a triangle mesh ``faces (F, 3)`` for contour tests.

    Returns ``(pair_edges (E, 2), pair_faces (E, 2), fixed_edges (M, 2))``: the edges shared by exactly
    two faces, with those faces (a contour when they face opposite ways), and the edges that are always
    contours: boundary and non-manifold edges, and edges between a neck face and a head face.
    """
    if faces.size == 0:
        empty = np.zeros((0, 2), dtype=np.int64)
        return empty, empty, empty
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(faces)), 3)
    key = edges[:, 0] * (int(faces.max()) + 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    key, edges, owner = key[order], edges[order], owner[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    paired = starts[counts == 2]
    pair_edges = edges[paired]
    pair_faces = np.stack([owner[paired], owner[paired + 1]], axis=1)
    neck_line = neck[pair_faces[:, 0]] != neck[pair_faces[:, 1]]
    fixed = np.concatenate([edges[starts[counts != 2]], pair_edges[neck_line]])
    return pair_edges[~neck_line], pair_faces[~neck_line], fixed


def _candidate_region(
    points: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int
) -> np.ndarray:
    """``(H, W)`` uint8, 1 at the pixels whose centres may see a triangle of ``points (P, 3)``.

    With every point in front of the camera, a triangle projects inside the convex hull of the projected
    points: the hull is filled (boundary pixels included, then grown by one pixel against round-off).
    Otherwise (or for projections too far off to fill) every pixel is a candidate.
    """
    import cv2

    region = np.zeros((height, width), dtype=np.uint8)
    if points.shape[0] == 0:
        return region
    cam = _camera_points(points, w2c)
    if np.any(cam[:, 2] <= NEAR_PLANE):
        return np.ones_like(region)
    px = _pinhole_pixels(cam, K)
    lo = np.array([px[:, 0].min(), px[:, 1].min()])
    hi = np.array([px[:, 0].max(), px[:, 1].max()])
    if hi[0] < -1 or hi[1] < -1 or lo[0] > width or lo[1] > height:
        return region
    if np.abs(px).max() > 1e6:  # beyond the fixed-point range of the hull fill: cast everything
        return np.ones_like(region)
    hull = cv2.convexHull(np.round(px * 16).astype(np.int32))
    cv2.fillConvexPoly(region, hull, 1, lineType=cv2.LINE_8, shift=4)
    return cv2.dilate(region, np.ones((3, 3), np.uint8))


def mesh_mask(vertices: Any, faces: Any, neck_face_mask: Any, K: Any, w2c: Any, size: Any) -> np.ndarray:
    """Silhouette of a mesh seen by a pinhole camera, cut below the neck line (:class:`MeshSilhouette`,
    method ``"auto"``).

    Args:
        vertices: ``(V, 3)`` canonical-space vertices; faces: ``(F, 3)`` int.
        neck_face_mask: ``(F,)`` bool, True for faces below the neck line; None keeps every face.
        K: ``(3, 3)`` intrinsics of the stored (undistorted) image; w2c: ``(4, 4)`` world→camera.
        size: ``(width, height)`` or an int for a square image.
    Returns:
        ``(H, W)`` bool.
    """
    return MeshSilhouette(vertices, faces, neck_face_mask).mask(K, w2c, size)
