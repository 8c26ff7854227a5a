"""UV binding: texel -> (face, barycentric) maps of a template, and interpolation of vertex data into UV.

One Gaussian per texel of an ``S x S`` UV map (RGCA). Texel ``(row i, column j)`` has its centre at
``u = (j + 0.5) / S`` and ``v = 1 - (i + 0.5) / S``: row 0 is the top of the texture image, where OBJ's ``v``
is 1 (the flip goliath's ``GeometryModule`` applies with ``flip_uv=True``).

The UV layout is rasterised as a 2D mesh at the texel centres with exact barycentrics. A texel centre on an
edge belongs to both faces; where UV triangles overlap, the lowest face index wins, so the maps are
deterministic. Texels outside every chart are invalid: face ``-1``, zero barycentrics, zero values.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from relightanyone.render.mesh import load_obj, validate_textured_mesh, vertex_normals

# Candidate (face, texel) pairs tested at once; bounds memory to a few hundred MB at 1024^2.
_CANDIDATES_PER_CHUNK = 4_000_000
# Inside test tolerance on barycentrics, so texel centres exactly on an edge are kept.
_EDGE_EPS = 1e-9


def texel_centre_uvs(size: int) -> np.ndarray:
    """``(S, S, 2)`` float64 UV coordinates of the texel centres (``[..., 0]`` = u, ``[..., 1]`` = v)."""
    centres = (np.arange(size, dtype=np.float64) + 0.5) / size
    u = np.broadcast_to(centres[None, :], (size, size))
    v = np.broadcast_to(1.0 - centres[:, None], (size, size))
    return np.stack([u, v], axis=-1)


def rasterize_uv_layout(uvs: np.ndarray, face_uvs: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise UV triangles at texel centres.

    Vectorised over (face, texel) candidates from each face's bounding box, in chunks of faces.

    Args:
        uvs: ``(T, 2)`` texture coordinates (u right, v up).
        face_uvs: ``(F, 3)`` int indices into ``uvs``.
        size: UV map size ``S``.

    Returns:
        face_index ``(S, S)`` int64 (``-1`` where no face covers the texel centre) and
        barycentrics ``(S, S, 3)`` float64 (weights of the face's three corners).
    """
    if size < 1:
        raise ValueError(f"UV size must be positive, got {size}")
    # Continuous texel coordinates: texel centres sit on integers (column, row).
    corners = uvs[face_uvs]  # (F, 3, 2)
    cols = corners[..., 0] * size - 0.5
    rows = (1.0 - corners[..., 1]) * size - 0.5
    points = np.stack([cols, rows], axis=-1)
    edge1 = points[:, 1] - points[:, 0]
    edge2 = points[:, 2] - points[:, 0]
    det = edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0]

    col_lo = np.clip(np.ceil(cols.min(1) - _EDGE_EPS), 0, size)
    col_hi = np.clip(np.floor(cols.max(1) + _EDGE_EPS), -1, size - 1)
    row_lo = np.clip(np.ceil(rows.min(1) - _EDGE_EPS), 0, size)
    row_hi = np.clip(np.floor(rows.max(1) + _EDGE_EPS), -1, size - 1)
    widths = np.maximum(col_hi - col_lo + 1, 0).astype(np.int64)
    heights = np.maximum(row_hi - row_lo + 1, 0).astype(np.int64)
    counts = np.where(np.abs(det) > 1e-12, widths * heights, 0)

    face_index = np.full(size * size, -1, dtype=np.int64)
    barycentrics = np.zeros((size * size, 3), dtype=np.float64)
    ends = np.cumsum(counts)
    start_face = 0
    while start_face < len(counts):
        # Largest run of faces whose candidates fit in one chunk (at least one face).
        limit = (ends[start_face - 1] if start_face else 0) + _CANDIDATES_PER_CHUNK
        stop_face = max(int(np.searchsorted(ends, limit, side="right")), start_face + 1)
        chunk = np.arange(start_face, stop_face)
        chunk_counts = counts[chunk]
        face_ids = np.repeat(chunk, chunk_counts)
        if len(face_ids):
            first = np.cumsum(chunk_counts) - chunk_counts
            local = np.arange(len(face_ids)) - np.repeat(first, chunk_counts)
            texel_row = row_lo[face_ids].astype(np.int64) + local // widths[face_ids]
            texel_col = col_lo[face_ids].astype(np.int64) + local % widths[face_ids]
            offset_x = texel_col - points[face_ids, 0, 0]
            offset_y = texel_row - points[face_ids, 0, 1]
            e1, e2, d = edge1[face_ids], edge2[face_ids], det[face_ids]
            b1 = (offset_x * e2[:, 1] - offset_y * e2[:, 0]) / d
            b2 = (e1[:, 0] * offset_y - e1[:, 1] * offset_x) / d
            b0 = 1.0 - b1 - b2
            inside = (b0 >= -_EDGE_EPS) & (b1 >= -_EDGE_EPS) & (b2 >= -_EDGE_EPS)
            texel = (texel_row * size + texel_col)[inside]
            # Candidates come in increasing face order, so the first hit per texel is the lowest face.
            texel_unique, first_hit = np.unique(texel, return_index=True)
            free = face_index[texel_unique] < 0
            chosen = first_hit[free]
            target = texel_unique[free]
            face_index[target] = face_ids[inside][chosen]
            weights = np.stack([b0, b1, b2], axis=-1)[inside][chosen]
            barycentrics[target] = np.clip(weights, 0.0, 1.0) / np.clip(weights, 0.0, 1.0).sum(
                -1, keepdims=True
            )
        start_face = stop_face
    return face_index.reshape(size, size), barycentrics.reshape(size, size, 3)


@dataclass
class UVBinding:
    """Texel -> (face, barycentric) binding of a template at one UV size.

    Attributes:
        size: ``S``.
        faces: ``(F, 3)`` int64 vertex indices of the template.
        uvs: ``(T, 2)`` float64 texture coordinates; ``face_uvs``: ``(F, 3)`` int64.
        face_index: ``(S, S)`` int64, ``-1`` where invalid.
        barycentrics: ``(S, S, 3)`` float32, zero where invalid.
        valid: ``(S, S)`` bool.
        num_vertices: ``V`` of the template.
    """

    size: int
    faces: torch.Tensor
    uvs: torch.Tensor
    face_uvs: torch.Tensor
    face_index: torch.Tensor
    barycentrics: torch.Tensor
    valid: torch.Tensor
    num_vertices: int
    _corner_cache: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = field(
        default=None, init=False, repr=False, compare=False
    )

    @classmethod
    def from_mesh(
        cls,
        vertices: np.ndarray | torch.Tensor,
        faces: np.ndarray | torch.Tensor,
        uvs: np.ndarray | torch.Tensor,
        face_uvs: np.ndarray | torch.Tensor,
        size: int,
    ) -> UVBinding:
        """Bind a template: ``vertices (V, 3)``, ``faces (F, 3)``, ``uvs (T, 2)``, ``face_uvs (F, 3)``."""
        vertices_np, faces_np, uvs_np, face_uvs_np = (
            _to_numpy(vertices, np.float64),
            _to_numpy(faces, np.int64),
            _to_numpy(uvs, np.float64),
            _to_numpy(face_uvs, np.int64),
        )
        validate_textured_mesh(vertices_np, faces_np, uvs_np, face_uvs_np, source="UVBinding.from_mesh")
        face_index, barycentrics = rasterize_uv_layout(uvs_np, face_uvs_np, size)
        return cls(
            size=size,
            faces=torch.from_numpy(faces_np),
            uvs=torch.from_numpy(uvs_np),
            face_uvs=torch.from_numpy(face_uvs_np),
            face_index=torch.from_numpy(face_index),
            barycentrics=torch.from_numpy(barycentrics.astype(np.float32)),
            valid=torch.from_numpy(face_index >= 0),
            num_vertices=len(vertices_np),
        )

    @classmethod
    def from_obj(cls, path: str | Path, size: int) -> UVBinding:
        """Bind the template stored in an OBJ file (see :func:`relightanyone.render.mesh.load_obj`)."""
        mesh = load_obj(path)
        return cls.from_mesh(mesh.vertices, mesh.faces, mesh.uvs, mesh.face_uvs, size)

    def to(self, device: torch.device | str) -> UVBinding:
        """Copy of the binding with every tensor on ``device``."""
        return UVBinding(
            size=self.size,
            faces=self.faces.to(device),
            uvs=self.uvs.to(device),
            face_uvs=self.face_uvs.to(device),
            face_index=self.face_index.to(device),
            barycentrics=self.barycentrics.to(device),
            valid=self.valid.to(device),
            num_vertices=self.num_vertices,
        )

    @property
    def valid_texels(self) -> torch.Tensor:
        """``(P,)`` int64 flat indices (``i * S + j``) of the valid texels."""
        return torch.nonzero(self.valid.reshape(-1), as_tuple=False).squeeze(1)

    def _valid_corners(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat valid texel indices ``(P,)``, their faces ``(P,)`` and barycentrics ``(P, 3)`` (cached)."""
        if self._corner_cache is None:
            texels = self.valid_texels
            faces = self.face_index.reshape(-1)[texels]
            self._corner_cache = (texels, faces, self.barycentrics.reshape(-1, 3)[texels])
        return self._corner_cache

    def _scatter(self, texels: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """(B, P, C) values at valid texels -> (B, C, S, S) with zeros elsewhere."""
        batch, _, channels = values.shape
        out = values.new_zeros(batch, self.size * self.size, channels)
        out = out.index_copy(1, texels, values)
        return out.permute(0, 2, 1).reshape(batch, channels, self.size, self.size)

    def interpolate(self, vertex_values: torch.Tensor) -> torch.Tensor:
        """Barycentric interpolation of per-vertex values into UV space, differentiable.

        Args:
            vertex_values: ``(B, V, C)``.

        Returns:
            ``(B, C, S, S)``; zero at invalid texels.
        """
        if vertex_values.ndim != 3 or vertex_values.shape[1] != self.num_vertices:
            raise ValueError(
                f"vertex_values must be (B, {self.num_vertices}, C) for this template, got {tuple(vertex_values.shape)}"
            )
        texels, faces, bary = self._valid_corners()
        corner_vertices = self.faces[faces]  # (P, 3)
        gathered = vertex_values[:, corner_vertices]  # (B, P, 3, C)
        values = (gathered * bary.to(vertex_values.dtype)[None, :, :, None]).sum(2)
        return self._scatter(texels, values)

    def interpolate_normals(self, vertices: torch.Tensor) -> torch.Tensor:
        """Unit normals per texel from the smooth (area-weighted) vertex normals of ``vertices (B, V, 3)``.

        Returns:
            ``(B, 3, S, S)``; zero at invalid texels.
        """
        normals = vertex_normals(vertices, self.faces)
        return F.normalize(self.interpolate(normals), dim=1)

    def texel_uvs(self) -> torch.Tensor:
        """``(S, S, 2)`` UV interpolated from each valid texel's face corners (zero where invalid)."""
        texels, faces, bary = self._valid_corners()
        corner_uvs = self.uvs[self.face_uvs[faces]]  # (P, 3, 2)
        values = (corner_uvs * bary.to(corner_uvs.dtype)[..., None]).sum(1)
        return self._scatter(texels, values[None])[0].permute(1, 2, 0)

    def tangent_frames(self, vertices: torch.Tensor) -> torch.Tensor:
        """Per-texel orthonormal tangent frames ``[T B N]`` for residual normals and rotations.

        ``N`` is the interpolated smooth normal; ``T`` is the face's ``dP/du`` (from its UV parameterisation)
        made orthogonal to ``N``; ``B = N x T`` so every frame is a proper rotation, also on mirrored charts.

        Args:
            vertices: ``(B, V, 3)``.

        Returns:
            ``(B, 3, 3, S, S)``: ``frames[b, :, k, i, j]`` is column ``k`` (T, B, N) of texel ``(i, j)``'s
            rotation matrix (local -> object). Zero at invalid texels.
        """
        texels, faces, _ = self._valid_corners()
        normal = self.interpolate_normals(vertices).flatten(2)[:, :, texels].permute(0, 2, 1)  # (B, P, 3)
        tangent = _face_tangents(vertices, self.faces, self.uvs.to(vertices.dtype), self.face_uvs)[:, faces]
        tangent = tangent - (tangent * normal).sum(-1, keepdim=True) * normal
        # Fallback where the UV parameterisation is degenerate: any direction perpendicular to N.
        axis_x = torch.zeros_like(normal)
        axis_x[..., 0] = 1.0
        axis_y = torch.zeros_like(normal)
        axis_y[..., 1] = 1.0
        helper = torch.where(normal[..., :1].abs() < 0.9, axis_x, axis_y)
        fallback = torch.cross(normal, helper, dim=-1)
        tangent = torch.where(tangent.norm(dim=-1, keepdim=True) > 1e-8, tangent, fallback)
        tangent = F.normalize(tangent, dim=-1)
        bitangent = torch.cross(normal, tangent, dim=-1)
        frames = torch.stack([tangent, bitangent, normal], dim=-1)  # (B, P, 3, 3)
        batch = frames.shape[0]
        flat = self._scatter(texels, frames.reshape(batch, -1, 9))  # (B, 9, S, S)
        return flat.reshape(batch, 3, 3, self.size, self.size)


def _face_tangents(
    vertices: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor, face_uvs: torch.Tensor
) -> torch.Tensor:
    """``dP/du`` per face, ``(B, F, 3)``, from positions ``(B, V, 3)`` and the UV parameterisation."""
    p0, p1, p2 = (vertices[:, faces[:, k]] for k in range(3))
    t0, t1, t2 = (uvs[face_uvs[:, k]] for k in range(3))
    edge1, edge2 = p1 - p0, p2 - p0
    duv1, duv2 = t1 - t0, t2 - t0
    det = duv1[:, 0] * duv2[:, 1] - duv2[:, 0] * duv1[:, 1]
    inv = torch.where(
        det.abs() > 1e-12, 1.0 / torch.where(det == 0, torch.ones_like(det), det), torch.zeros_like(det)
    )
    return (edge1 * duv2[:, 1, None] - edge2 * duv1[:, 1, None]) * inv[:, None]


def _to_numpy(array: np.ndarray | torch.Tensor, dtype: type) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().numpy()
    return np.ascontiguousarray(array, dtype=dtype)
