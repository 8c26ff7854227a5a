"""Mesh helpers: OBJ loading that keeps UV seams, and differentiable face / vertex normals.

A textured mesh keeps two index sets, as the OBJ file does: ``faces`` index the 3D vertices (one vertex per
surface point, so normals and deformations stay smooth across UV seams) and ``face_uvs`` index the texture
coordinates (a seam vertex has one UV per chart it belongs to). UVs follow the OBJ convention: ``u`` to the
right, ``v`` up, both in [0, 1].
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from relightanyone.render.errors import FileFormatError


@dataclass(frozen=True)
class TexturedMesh:
    """A triangle mesh with per-corner texture coordinates.

    Attributes:
        vertices: ``(V, 3)`` float64 positions (the file's units).
        faces: ``(F, 3)`` int64 vertex indices.
        uvs: ``(T, 2)`` float64 texture coordinates (u right, v up).
        face_uvs: ``(F, 3)`` int64 indices into ``uvs``, corner by corner with ``faces``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray

    def __post_init__(self) -> None:
        validate_textured_mesh(self.vertices, self.faces, self.uvs, self.face_uvs, source="TexturedMesh")


def validate_textured_mesh(
    vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, face_uvs: np.ndarray, source: str
) -> None:
    """Raise ``ValueError`` naming ``source`` and the field when shapes or indices are inconsistent."""
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{source}: vertices must be (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{source}: faces must be (F, 3) triangles, got {faces.shape}")
    if uvs.ndim != 2 or uvs.shape[1] != 2:
        raise ValueError(f"{source}: uvs must be (T, 2), got {uvs.shape}")
    if face_uvs.shape != faces.shape:
        raise ValueError(f"{source}: face_uvs {face_uvs.shape} must match faces {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"{source}: faces index vertices outside [0, {len(vertices)})")
    if face_uvs.size and (face_uvs.min() < 0 or face_uvs.max() >= len(uvs)):
        raise ValueError(f"{source}: face_uvs index texture coordinates outside [0, {len(uvs)})")


def load_obj(path: str | Path) -> TexturedMesh:
    """Load a triangulated OBJ with texture coordinates, keeping the 3D topology and the UV seams.

    trimesh is asked twice: once in file order (vertices and faces as written) and once with UVs, where it
    splits seam vertices; the second load's per-corner indices become ``face_uvs``.

    Args:
        path: ``.obj`` file with ``v``, ``vt`` and ``f v/vt`` records.

    Returns:
        :class:`TexturedMesh`.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: OBJ file not found")
    with warnings.catch_warnings():
        # trimesh warns about texture-less materials while building its visuals; irrelevant here.
        warnings.simplefilter("ignore", RuntimeWarning)
        ordered = trimesh.load(path, process=False, maintain_order=True, force="mesh")
        split = trimesh.load(path, process=False, force="mesh")
    uv = getattr(split.visual, "uv", None)
    if uv is None:
        raise FileFormatError(f"{path}: no texture coordinates ('vt' records referenced by faces) found")
    faces = np.asarray(ordered.faces, dtype=np.int64)
    face_uvs = np.asarray(split.faces, dtype=np.int64)
    if faces.shape != face_uvs.shape or not np.allclose(
        np.asarray(ordered.vertices)[faces], np.asarray(split.vertices)[face_uvs]
    ):
        raise FileFormatError(
            f"{path}: could not match faces to texture coordinates (mixed groups or quads?)"
        )
    return TexturedMesh(
        vertices=np.asarray(ordered.vertices, dtype=np.float64),
        faces=faces,
        uvs=np.asarray(uv, dtype=np.float64),
        face_uvs=face_uvs,
    )


def face_normals(vertices: torch.Tensor, faces: torch.Tensor, normalize: bool = True) -> torch.Tensor:
    """Per-face normals ``(v1 - v0) x (v2 - v0)`` (counter-clockwise faces point outwards).

    Args:
        vertices: ``(..., V, 3)``.
        faces: ``(F, 3)`` int64.
        normalize: unit length if True, else twice the face area in length.

    Returns:
        ``(..., F, 3)``.
    """
    v0 = vertices[..., faces[:, 0], :]
    v1 = vertices[..., faces[:, 1], :]
    v2 = vertices[..., faces[:, 2], :]
    normals = torch.cross(v1 - v0, v2 - v0, dim=-1)
    return torch.nn.functional.normalize(normals, dim=-1) if normalize else normals


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals, differentiable.

    Each vertex sums the unnormalised normals of its faces (so a sliver face, whose direction is noise,
    weighs little) and normalises. Unreferenced vertices get a zero vector.

    Args:
        vertices: ``(..., V, 3)`` float.
        faces: ``(F, 3)`` int64.

    Returns:
        ``(..., V, 3)``.
    """
    weighted = face_normals(vertices, faces, normalize=False)  # (..., F, 3)
    accumulated = torch.zeros_like(vertices)
    for corner in range(3):
        accumulated = accumulated.index_add(-2, faces[:, corner], weighted)
    return torch.nn.functional.normalize(accumulated, dim=-1)


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` float64 and triangles ``(F, 3)`` int64 (0-based) of an OBJ file.

    Only ``v`` and ``f`` records are read (texture indices after ``/`` are ignored) and vertex order is
    kept exactly, which the template topology relies on; polygons are fanned into triangles.
    """
    path = Path(path)
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise FileFormatError(f"{path}: cannot read mesh ({error.strerror or error})") from None
    for number, line in enumerate(text.splitlines(), start=1):
        if line.startswith("v "):
            parts = line.split()
            if len(parts) < 4:
                raise FileFormatError(f"{path}:{number}: vertex needs 3 coordinates")
            vertices.append([float(parts[1]), float(parts[2]), float(parts[3])])
        elif line.startswith("f "):
            index = [int(token.split("/")[0]) for token in line.split()[1:]]
            index = [i - 1 if i > 0 else len(vertices) + i for i in index]
            faces.extend([index[0], index[k], index[k + 1]] for k in range(1, len(index) - 1))
    if not vertices:
        raise FileFormatError(f"{path}: no vertices found (not an OBJ mesh?)")
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not np.all(np.isfinite(V)):
        raise FileFormatError(f"{path}: vertices hold NaN or infinite coordinates")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise FileFormatError(f"{path}: faces index vertices outside 1..{len(V)}")
    return V, F


def faces_touching(vertex_mask: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(F,)`` bool: faces with at least one vertex in ``vertex_mask (V,)`` (the neck cut's face rule)."""
    return np.asarray(vertex_mask, dtype=bool)[faces].any(axis=1)


def read_obj_vertices(path: str | Path, expected: int | None = None) -> np.ndarray:
    """Vertices ``(V, 3)`` of an OBJ (fast path: ``v`` records only, order kept); raises naming the file
    when it is unreadable or when ``expected`` vertices are not there."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise FileFormatError(f"{path}: cannot read mesh ({error.strerror or error})") from None
    lines = [line[2:] for line in text.split("\n") if line.startswith("v ")]
    if not lines:
        raise FileFormatError(f"{path}: no vertices found (not an OBJ mesh?)")
    try:
        # One C-level parse of all numbers; records with a w or colour column take the per-line path.
        numbers = np.array(" ".join(lines).split(), dtype=np.float64)
        if numbers.size == 3 * len(lines) and len(lines[0].split()) == 3:
            vertices = numbers.reshape(-1, 3)
        else:
            vertices = np.asarray([line.split()[:3] for line in lines], dtype=np.float64)
    except ValueError:
        raise FileFormatError(f"{path}: a vertex record does not hold 3 numbers") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise FileFormatError(f"{path}: a vertex record does not hold 3 numbers")
    if not np.all(np.isfinite(vertices)):
        raise FileFormatError(f"{path}: vertices hold NaN or infinite coordinates")
    if expected is not None and len(vertices) != expected:
        raise FileFormatError(
            f"{path}: mesh has {len(vertices)} vertices but the template has {expected} "
            "(a different topology?)"
        )
    return vertices
