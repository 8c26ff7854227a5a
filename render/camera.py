"""The one camera type of the toolkit: batched OpenCV pinhole cameras with lens distortion.

Conventions (``docs/cameras.md``): camera axes x right, y down, z forward; ``w2c`` maps world points (metres)
to camera coordinates; ``K`` is in pixels of the stored image and the centre of pixel (u, v) is at (u, v);
``dist`` holds OpenCV coefficients ``(k1, k2, p1, p2, k3[, k4, k5, k6])``. Projection reproduces
``cv2.projectPoints`` (plus the skew term ``K[0, 1]`` that OpenCV ignores), so any camera read here can be
checked against OpenCV directly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from kornia.geometry.calibration import distort_points, undistort_points

# Lengths of OpenCV coefficient vectors we store: the 5-term Brown-Conrady model and the 8-term rational model.
DIST_LENGTHS = (5, 8)


def pad_distortion(dist: torch.Tensor) -> torch.Tensor:
    """Zero-pad OpenCV coefficients to 5 (k1, k2, p1, p2, k3) or 8 (rational model) terms.

    Args:
        dist: (..., D) with D in 0..8.
    Returns:
        (..., 5) when D <= 5, else (..., 8).
    """
    d = dist.shape[-1]
    if d > 8:
        raise ValueError(f"at most 8 OpenCV distortion coefficients are supported, got {d}")
    target = 5 if d <= 5 else 8
    return torch.nn.functional.pad(dist, (0, target - d))


def _index_tensor(index: int | slice | Sequence[int] | torch.Tensor, batch: int) -> torch.Tensor:
    """Turn any batch index into a 1-D long tensor of positions (an int keeps its batch axis)."""
    positions = torch.arange(batch)
    if isinstance(index, int):
        if not -batch <= index < batch:
            raise IndexError(f"camera index {index} out of range for {batch} cameras")
        return positions[[index]]
    if isinstance(index, slice):
        return positions[index]
    index_tensor = torch.as_tensor(index)
    if index_tensor.dtype == torch.bool:
        return positions[index_tensor]
    return positions[index_tensor.long().reshape(-1)]


@dataclass(frozen=True, eq=False)
class Cameras:
    """A batch of B OpenCV cameras.

    Attributes:
        K: (B, 3, 3) intrinsics in pixels of the stored image (``K[0, 1]`` is skew).
        w2c: (B, 4, 4) world-to-camera rigid transforms, float64 by default, metres.
        dist: (B, 5) or (B, 8) OpenCV distortion coefficients, zero-padded.
        width: (B,) int64 image widths in pixels.
        height: (B,) int64 image heights in pixels.
        names: optional camera names, one per camera.
    """

    K: torch.Tensor
    w2c: torch.Tensor
    dist: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    names: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        batch = self.K.shape[0] if self.K.dim() == 3 else -1
        if self.K.dim() != 3 or self.K.shape[1:] != (3, 3):
            raise ValueError(f"Cameras.K must be (B, 3, 3), got {tuple(self.K.shape)}")
        if self.w2c.shape != (batch, 4, 4):
            raise ValueError(f"Cameras.w2c must be ({batch}, 4, 4), got {tuple(self.w2c.shape)}")
        if self.dist.dim() != 2 or self.dist.shape[0] != batch or self.dist.shape[1] not in DIST_LENGTHS:
            raise ValueError(
                f"Cameras.dist must be ({batch}, 5) or ({batch}, 8), got {tuple(self.dist.shape)}"
            )
        for field in ("width", "height"):
            value = getattr(self, field)
            if value.shape != (batch,) or value.dtype.is_floating_point:
                raise ValueError(f"Cameras.{field} must be an integer tensor of shape ({batch},)")
        if self.names is not None and len(self.names) != batch:
            raise ValueError(f"Cameras.names has {len(self.names)} entries for {batch} cameras")

    # ------------------------------------------------------------------ construction
    @staticmethod
    def create(
        K: torch.Tensor,
        w2c: torch.Tensor,
        width: int | Sequence[int] | torch.Tensor,
        height: int | Sequence[int] | torch.Tensor,
        dist: torch.Tensor | None = None,
        names: Sequence[str] | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> Cameras:
        """Build cameras from (B, 3, 3) K, (B, 4, 4) or (B, 3, 4) w2c and optional (B, D<=8) distortion.

        Single (3, 3) / (4, 4) inputs make a batch of one; a scalar width/height is shared by the batch.
        """
        K = torch.as_tensor(K, dtype=dtype)
        w2c = torch.as_tensor(w2c, dtype=dtype)
        if K.dim() == 2:
            K = K[None]
        if w2c.dim() == 2:
            w2c = w2c[None]
        if w2c.shape[-2:] == (3, 4):
            bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype).expand(w2c.shape[0], 1, 4)
            w2c = torch.cat([w2c, bottom], dim=1)
        batch = K.shape[0]
        if dist is None:
            dist = torch.zeros(batch, 5, dtype=dtype)
        dist = torch.as_tensor(dist, dtype=dtype)
        if dist.dim() == 1:
            dist = dist[None]
        sizes = [torch.as_tensor(v, dtype=torch.int64).reshape(-1) for v in (width, height)]
        if any(v.numel() not in (1, batch) for v in sizes):
            raise ValueError(f"width and height need 1 or {batch} values")
        width_t, height_t = (v.expand(batch).clone() for v in sizes)
        return Cameras(
            K=K,
            w2c=w2c,
            dist=pad_distortion(dist),
            width=width_t,
            height=height_t,
            names=tuple(names) if names is not None else None,
        )

    @staticmethod
    def from_c2w(
        K: torch.Tensor,
        c2w: torch.Tensor,
        width: int | Sequence[int] | torch.Tensor,
        height: int | Sequence[int] | torch.Tensor,
        dist: torch.Tensor | None = None,
        names: Sequence[str] | None = None,
    ) -> Cameras:
        """Build cameras from (B, 4, 4) camera-to-world transforms in OpenCV axes."""
        c2w = torch.as_tensor(c2w, dtype=torch.float64)
        return Cameras.create(K, rigid_inverse(c2w), width, height, dist, names, dtype=torch.float64)

    # ------------------------------------------------------------------ batching
    def __len__(self) -> int:
        return self.K.shape[0]

    def __getitem__(self, index: int | slice | Sequence[int] | torch.Tensor) -> Cameras:
        """Select cameras; an integer index keeps the batch axis (B = 1)."""
        positions = _index_tensor(index, len(self))
        names = tuple(self.names[i] for i in positions.tolist()) if self.names is not None else None
        pos = positions.to(self.K.device)
        return Cameras(
            K=self.K[pos],
            w2c=self.w2c[pos],
            dist=self.dist[pos],
            width=self.width[positions.to(self.width.device)],
            height=self.height[positions.to(self.height.device)],
            names=names,
        )

    @staticmethod
    def cat(cameras: Sequence[Cameras]) -> Cameras:
        """Concatenate batches; distortion is zero-padded to the longest model. Names are kept if all have them."""
        if len(cameras) == 0:
            raise ValueError("Cameras.cat needs at least one Cameras")
        dist_len = max(c.dist.shape[1] for c in cameras)
        dists = [torch.nn.functional.pad(c.dist, (0, dist_len - c.dist.shape[1])) for c in cameras]
        names = None
        if all(c.names is not None for c in cameras):
            names = tuple(n for c in cameras for n in c.names)  # type: ignore[union-attr]
        return Cameras(
            K=torch.cat([c.K for c in cameras]),
            w2c=torch.cat([c.w2c for c in cameras]),
            dist=torch.cat(dists),
            width=torch.cat([c.width for c in cameras]),
            height=torch.cat([c.height for c in cameras]),
            names=names,
        )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Cameras:
        """Move to a device and/or cast the floating tensors (K, w2c, dist) to ``dtype``."""
        return Cameras(
            K=self.K.to(device=device, dtype=dtype),
            w2c=self.w2c.to(device=device, dtype=dtype),
            dist=self.dist.to(device=device, dtype=dtype),
            width=self.width.to(device=device),
            height=self.height.to(device=device),
            names=self.names,
        )

    def with_names(self, names: Sequence[str]) -> Cameras:
        """The same cameras under new names."""
        return Cameras(self.K, self.w2c, self.dist, self.width, self.height, tuple(names))

    # ------------------------------------------------------------------ geometry
    @property
    def R(self) -> torch.Tensor:
        """(B, 3, 3) world-to-camera rotations."""
        return self.w2c[:, :3, :3]

    @property
    def t(self) -> torch.Tensor:
        """(B, 3) world-to-camera translations."""
        return self.w2c[:, :3, 3]

    @property
    def c2w(self) -> torch.Tensor:
        """(B, 4, 4) camera-to-world transforms (OpenCV axes)."""
        return rigid_inverse(self.w2c)

    @property
    def centers(self) -> torch.Tensor:
        """(B, 3) camera positions in world coordinates, ``-R^T t``."""
        return -(self.R.transpose(1, 2) @ self.t[..., None])[..., 0]

    @property
    def look_dirs(self) -> torch.Tensor:
        """(B, 3) unit optical-axis directions (camera +z) in world coordinates, row 2 of R."""
        return self.R[:, 2, :]

    @property
    def is_distorted(self) -> bool:
        """True when any camera has a non-zero distortion coefficient."""
        return bool((self.dist != 0).any())

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """Camera-frame coordinates of world points.

        Args:
            points: (N, 3) shared by all cameras, or (B, N, 3).
        Returns:
            (B, N, 3) points in each camera's frame.
        """
        points = self._batched_points(points, 3)
        R, t = self.R.to(points.dtype), self.t.to(points.dtype)
        return points @ R.transpose(1, 2) + t[:, None, :]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points to distorted pixel coordinates, as ``cv2.projectPoints`` does.

        Points behind the camera are projected too (their depth is <= 0); mask them with the returned depth.

        Args:
            points: (N, 3) shared by all cameras, or (B, N, 3), world coordinates.
        Returns:
            pixels: (B, N, 2) (u, v) with pixel centres on integers.
            depth: (B, N) camera-frame z.
        """
        cam = self.world_to_camera(points)
        depth = cam[..., 2]
        normalized = cam[..., :2] / depth[..., None]
        return self.normalized_to_pixels(normalized), depth

    def normalized_to_pixels(self, normalized: torch.Tensor) -> torch.Tensor:
        """Apply lens distortion and K to points on the z = 1 plane: (B, N, 2) -> (B, N, 2) pixels."""
        dist = self.dist.to(normalized.dtype)
        if self.is_distorted:
            identity = torch.eye(3, dtype=normalized.dtype, device=normalized.device).expand(len(self), 3, 3)
            normalized = distort_points(normalized, identity, dist)
        K = self.K.to(normalized.dtype)
        u = K[:, None, 0, 0] * normalized[..., 0] + K[:, None, 0, 1] * normalized[..., 1] + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * normalized[..., 1] + K[:, None, 1, 2]
        return torch.stack([u, v], dim=-1)

    def pixels_to_normalized(self, pixels: torch.Tensor, iterations: int = 20) -> torch.Tensor:
        """Undo K and lens distortion: (B, N, 2) pixels -> (B, N, 2) points on the z = 1 plane.

        The inverse of the distortion is the fixed-point iteration of ``cv2.undistortPoints`` (which stops after
        5 steps by default); more steps converge further inside the lens model's valid radius.
        """
        pixels = self._batched_points(pixels, 2)
        K = self.K.to(pixels.dtype)
        y = (pixels[..., 1] - K[:, None, 1, 2]) / K[:, None, 1, 1]
        x = (pixels[..., 0] - K[:, None, 0, 2] - K[:, None, 0, 1] * y) / K[:, None, 0, 0]
        normalized = torch.stack([x, y], dim=-1)
        if self.is_distorted:
            identity = torch.eye(3, dtype=pixels.dtype, device=pixels.device).expand(len(self), 3, 3)
            normalized = undistort_points(
                normalized, identity, self.dist.to(pixels.dtype), num_iters=iterations
            )
        return normalized

    def unproject(self, pixels: torch.Tensor, depth: torch.Tensor, iterations: int = 20) -> torch.Tensor:
        """World points seen at distorted pixels with the given camera-frame z-depth.

        Args:
            pixels: (B, N, 2) or (N, 2) pixel coordinates.
            depth: (B, N) or (N,) z-depth in world units.
        Returns:
            (B, N, 3) world points; ``project(unproject(p, d)) == (p, d)``.
        """
        normalized = self.pixels_to_normalized(pixels, iterations)
        depth = torch.as_tensor(depth, dtype=normalized.dtype, device=normalized.device)
        if depth.dim() == 1:
            depth = depth.expand(len(self), -1)
        cam = torch.cat([normalized, torch.ones_like(normalized[..., :1])], dim=-1) * depth[..., None]
        R, t = self.R.to(cam.dtype), self.t.to(cam.dtype)
        return (cam - t[:, None, :]) @ R

    def rays(self, pixels: torch.Tensor, iterations: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space rays through distorted pixels.

        Args:
            pixels: (B, N, 2) or (N, 2).
        Returns:
            origins: (B, N, 3) camera centres; directions: (B, N, 3) unit vectors.
        """
        normalized = self.pixels_to_normalized(pixels, iterations)
        cam_dirs = torch.cat([normalized, torch.ones_like(normalized[..., :1])], dim=-1)
        directions = cam_dirs @ self.R.to(cam_dirs.dtype)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        origins = self.centers.to(directions.dtype)[:, None, :].expand_as(directions)
        return origins, directions

    # ------------------------------------------------------------------ image-space edits
    def resize(self, scale: float | tuple[int, int]) -> Cameras:
        """Cameras for the image resized by ``scale`` or to ``(new_width, new_height)``.

        The new size is ``round(width * scale)`` (or the given size); each axis then uses its exact factor
        ``new / old`` in :func:`resize_intrinsics`.
        """
        if isinstance(scale, tuple | list):
            new_w = torch.full_like(self.width, int(scale[0]))
            new_h = torch.full_like(self.height, int(scale[1]))
        else:
            if not scale > 0:
                raise ValueError(f"resize scale must be positive, got {scale}")
            new_w = torch.round(self.width.double() * scale).long()
            new_h = torch.round(self.height.double() * scale).long()
        if bool((new_w <= 0).any() or (new_h <= 0).any()):
            raise ValueError("resize would produce an empty image")
        sx = (new_w.double() / self.width.double()).to(self.K)
        sy = (new_h.double() / self.height.double()).to(self.K)
        return Cameras(resize_intrinsics(self.K, sx, sy), self.w2c, self.dist, new_w, new_h, self.names)

    def crop(self, x0: int | torch.Tensor, y0: int | torch.Tensor, width: int, height: int) -> Cameras:
        """Cameras for the ``width x height`` crop whose top-left pixel is (x0, y0) (:func:`crop_intrinsics`)."""
        if width <= 0 or height <= 0:
            raise ValueError(f"crop size must be positive, got {width}x{height}")
        x0 = torch.as_tensor(x0, dtype=self.K.dtype, device=self.K.device)
        y0 = torch.as_tensor(y0, dtype=self.K.dtype, device=self.K.device)
        new_w = torch.full_like(self.width, int(width))
        new_h = torch.full_like(self.height, int(height))
        return Cameras(crop_intrinsics(self.K, x0, y0), self.w2c, self.dist, new_w, new_h, self.names)

    # ------------------------------------------------------------------ world edits
    def transform_world(self, similarity: torch.Tensor) -> Cameras:
        """Cameras for a world mapped by the similarity ``x_new = s R x_old + t`` (a 4x4 ``[[sR, t], [0, 1]]``).

        Camera frames are scaled with the world, so the result stays a rigid w2c in the new units:
        ``w2c_new = diag(s, s, s, 1) @ w2c @ inv(S)``. Pixels are unchanged and depths scale by ``s``.
        """
        S = torch.as_tensor(similarity, dtype=self.w2c.dtype, device=self.w2c.device)
        scale, _ = similarity_scale(S)
        scale_matrix = torch.diag(torch.stack([scale, scale, scale, torch.ones_like(scale)]))
        w2c = scale_matrix @ self.w2c @ torch.linalg.inv(S)
        # The bottom row is exactly [0, 0, 0, 1] in theory; reset it to drop the inverse's rounding.
        w2c[:, 3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=w2c.dtype, device=w2c.device)
        return Cameras(self.K, w2c, self.dist, self.width, self.height, self.names)

    # ------------------------------------------------------------------ exports
    def to_gsplat_viewmats(self) -> torch.Tensor:
        """(B, 4, 4) float32 world-to-camera matrices, the ``viewmats`` of ``gsplat.rasterization``."""
        return self.w2c.float()

    def to_gsplat_Ks(self) -> torch.Tensor:
        """(B, 3, 3) float32 intrinsics for gsplat (which ignores skew; cameras with skew are refused)."""
        if bool((self.K[:, 0, 1] != 0).any()):
            raise ValueError("gsplat has no skew term; these cameras have K[0, 1] != 0")
        return self.K.float()

    def _batched_points(self, points: torch.Tensor, dim: int) -> torch.Tensor:
        points = torch.as_tensor(points)
        if not points.dtype.is_floating_point:
            points = points.to(self.w2c.dtype)
        if points.dim() == 2:
            points = points.expand(len(self), -1, -1)
        if points.dim() != 3 or points.shape[0] != len(self) or points.shape[-1] != dim:
            raise ValueError(
                f"expected points of shape (N, {dim}) or ({len(self)}, N, {dim}), got {tuple(points.shape)}"
            )
        return points


def look_at_w2c(eye: Any, target: Any, up: Any) -> np.ndarray:
    """(4, 4) float64 world-to-camera matrix (OpenCV axes) of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that points up in the image (towards smaller v); it need not be
    perpendicular to the view direction, only not parallel to it. eye, target, up: (3,).
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    length = np.linalg.norm(right)
    if not length > 1e-12:
        raise ValueError(f"look-at: up {up.tolist()} is parallel to the view direction {forward.tolist()}")
    right = right / length
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera x, y, z in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ eye
    return w2c


def _copy_intrinsics(K: Any) -> Any:
    """A tensor's clone (same dtype and device), or anything else as a new float64 numpy array."""
    if isinstance(K, torch.Tensor):
        return K.clone()
    return np.array(K, dtype=np.float64, copy=True)


def resize_intrinsics(K: Any, sx: Any, sy: Any) -> Any:
    """Intrinsics of the image resized by ``sx`` along x and ``sy`` along y.

    Pixel centres sit on integers, so a pixel's centre ``c`` moves to ``(c + 0.5) * s - 0.5``; focals scale:
    ``fx *= sx``, ``fy *= sy``, and the skew ``K[0, 1] *= sx``.

    Args:
        K: (..., 3, 3) numpy array (or nested lists) or torch tensor.
        sx, sy: scale factors, scalars or arrays of K's batch shape (...).
    Returns:
        (..., 3, 3) new intrinsics: a tensor in K's dtype for a tensor, else float64 numpy.
    """
    K = _copy_intrinsics(K)
    K[..., 0, 0] *= sx
    K[..., 0, 1] *= sx
    K[..., 1, 1] *= sy
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


def crop_intrinsics(K: Any, x0: Any, y0: Any) -> Any:
    """Intrinsics of the crop whose top-left pixel is ``(x0, y0)``: ``c -= (x0, y0)``.

    Args:
        K: (..., 3, 3) numpy array (or nested lists) or torch tensor.
        x0, y0: crop origin in pixels, scalars or arrays of K's batch shape (...).
    Returns:
        (..., 3, 3) new intrinsics: a tensor in K's dtype for a tensor, else float64 numpy.
    """
    K = _copy_intrinsics(K)
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    return K


def rigid_inverse(transform: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid (..., 4, 4) transforms, ``[R^T, -R^T t]``, exact for orthonormal R."""
    R = transform[..., :3, :3]
    t = transform[..., :3, 3:]
    out = torch.zeros_like(transform)
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:] = -R.transpose(-1, -2) @ t
    out[..., 3, 3] = 1.0
    return out


def similarity_scale(similarity: torch.Tensor, tolerance: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a (4, 4) similarity ``[[sR, t], [0, 1]]`` into its scale ``s`` (scalar) and rotation R (3, 3).

    Raises ValueError when the linear part is not a positive multiple of a rotation.
    """
    if similarity.shape != (4, 4):
        raise ValueError(f"a similarity transform must be 4x4, got {tuple(similarity.shape)}")
    bottom = similarity[3].to(torch.float64).cpu()
    if not torch.allclose(bottom, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
        raise ValueError(f"a similarity transform must end with the row [0, 0, 0, 1], got {bottom.tolist()}")
    linear = similarity[:3, :3]
    det = torch.linalg.det(linear)
    if not bool(det > 0):
        raise ValueError(f"a similarity transform needs a positive determinant, got {float(det):.6g}")
    scale = det.abs() ** (1.0 / 3.0)
    rotation = linear / scale
    eye = torch.eye(3, dtype=linear.dtype, device=linear.device)
    error = float((rotation @ rotation.T - eye).abs().max())
    if error > tolerance:
        raise ValueError(
            f"the 3x3 part is not a uniform scale times a rotation (orthonormality error {error:.3g})"
        )
    return scale, rotation
