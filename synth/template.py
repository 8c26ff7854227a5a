"""The procedural template head: a closed, watertight surface with a UV layout.

The surface is star-shaped around the origin: every vertex is ``direction * radius(direction)`` on a
latitude-longitude grid, with a single vertex at each pole. That keeps it closed and free of
self-intersections whatever smooth radius field a subject adds on top (see :mod:`.subject`).

Canonical head space: metres, +y up, +z out of the face, origin near the head centre. Head height from
chin to crown is about 0.23 m; a neck stub reaches down to y = -0.20 m.

UV layout: equirectangular in the direction of each vertex. ``u`` is the longitude, 0.5 at the front
(+z) and increasing toward +x; ``v`` is 1 at the crown and 0 under the neck. The seam runs down the
back of the head (longitude +-pi), where the UV vertices are duplicated. Textures are stored with row 0
at ``v = 1`` (the usual OBJ image orientation).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# Head ellipsoid semi-axes (m): half width, half height, half depth.
HEAD_SEMI_AXES = (0.077, 0.118, 0.098)
NECK_RADIUS = 0.056
NECK_BOTTOM_Y = -0.20
NECK_AXIS_Z = -0.015  # the neck sits slightly behind the head centre
NECK_LINE_Y = -0.128  # vertices below this line form the neck mask
UNION_SHARPNESS = 10.0  # exponent of the smooth maximum joining head and neck

# Facial features as radial bumps: (centre direction target point, widths (x, y) in radians-ish, amplitude m).
FEATURES: dict[str, tuple[tuple[float, float, float], tuple[float, float], float]] = {
    "nose": ((0.0, -0.16, 1.0), (0.07, 0.15), 0.024),
    "nose_bridge": ((0.0, 0.08, 1.0), (0.05, 0.12), 0.008),
    "brow_left": ((0.36, 0.46, 1.0), (0.14, 0.05), 0.007),
    "brow_right": ((-0.36, 0.46, 1.0), (0.14, 0.05), 0.007),
    "eye_left": ((0.34, 0.24, 1.0), (0.09, 0.06), -0.009),
    "eye_right": ((-0.34, 0.24, 1.0), (0.09, 0.06), -0.009),
    "upper_lip": ((0.0, -0.62, 1.0), (0.15, 0.05), 0.008),
    "lower_lip": ((0.0, -0.80, 1.0), (0.13, 0.05), 0.008),
    "chin": ((0.0, -1.55, 1.0), (0.22, 0.16), 0.024),
    "cheek_left": ((0.6, -0.2, 1.0), (0.16, 0.14), 0.004),
    "cheek_right": ((-0.6, -0.2, 1.0), (0.16, 0.14), 0.004),
    "ear_left": ((1.0, 0.02, -0.08), (0.10, 0.20), 0.022),
    "ear_right": ((-1.0, 0.02, -0.08), (0.10, 0.20), 0.022),
}
# Directions that pull the lower face in to form a jaw line (negative = narrower).
JAW = ((0.0, -1.0, 0.45), (0.55, 0.25), -0.008)


@dataclass(frozen=True)
class HeadTemplate:
    """The template mesh all subjects share (same topology and UVs)."""

    vertices: np.ndarray  # (V, 3) float64 metres, canonical head space
    faces: np.ndarray  # (F, 3) int64 into vertices, counter-clockwise seen from outside
    uvs: np.ndarray  # (T, 2) float64 in [0, 1]
    face_uvs: np.ndarray  # (F, 3) int64 into uvs
    neck_mask: np.ndarray  # (V,) bool, vertices below the neck line
    landmarks: dict[str, int]  # name -> vertex index

    @property
    def directions(self) -> np.ndarray:
        """(V, 3) unit direction of every vertex from the origin (the surface is star-shaped)."""
        return self.vertices / np.linalg.norm(self.vertices, axis=1, keepdims=True)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def feature_weight(directions: np.ndarray, centre, widths) -> np.ndarray:
    """Smooth bump weight in [0, 1] of unit ``directions`` (N, 3) around the direction of ``centre``.

    ``widths`` (wx, wy) are Gaussian widths along the tangent directions "right" and "up" at the
    centre, in units of the unit sphere (roughly radians).
    """
    c = _unit(centre)
    up = np.array([0.0, 1.0, 0.0])
    right = np.cross(up, c)
    if np.linalg.norm(right) < 1e-9:
        right = np.array([1.0, 0.0, 0.0])
    right = _unit(right)
    true_up = np.cross(c, right)
    offset = directions - c
    dx = offset @ right
    dy = offset @ true_up
    front = directions @ c  # suppress the bump on the far side of the sphere
    w = np.exp(-0.5 * ((dx / widths[0]) ** 2 + (dy / widths[1]) ** 2))
    return w * (front > 0)


def ellipsoid_radius(directions: np.ndarray, semi_axes) -> np.ndarray:
    """(N,) distance from the centre to an axis-aligned ellipsoid along unit ``directions`` (N, 3)."""
    a = np.asarray(semi_axes, dtype=np.float64)
    return 1.0 / np.sqrt(((directions / a) ** 2).sum(axis=1))


def neck_radius(directions: np.ndarray) -> np.ndarray:
    """(N,) distance from the origin to the capped neck cylinder along unit ``directions``.

    The cylinder has axis x = 0, z = NECK_AXIS_Z, radius NECK_RADIUS, and is capped at NECK_BOTTOM_Y.
    Directions that point upward get a small radius so the smooth union ignores them.
    """
    d = directions
    # Ray-cylinder: |(t*dx, t*dz) - (0, zc)| = R  ->  t^2 (dx^2+dz^2) - 2 t dz zc + zc^2 - R^2 = 0.
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = -2.0 * d[:, 2] * NECK_AXIS_Z
    c = NECK_AXIS_Z**2 - NECK_RADIUS**2
    disc = np.maximum(b * b - 4 * a * c, 0.0)
    t_wall = (-b + np.sqrt(disc)) / np.maximum(2 * a, 1e-12)
    t_wall = np.where(a < 1e-12, np.inf, t_wall)
    t_cap = np.where(d[:, 1] < -1e-9, NECK_BOTTOM_Y / np.minimum(d[:, 1], -1e-9), np.inf)
    t = np.minimum(t_wall, t_cap)
    # Only the part below the head centre is neck; above it the neck contributes nothing.
    return np.where(d[:, 1] < -0.05, t, 0.0)


def template_radius(directions: np.ndarray) -> np.ndarray:
    """(N,) radius of the template surface along unit ``directions`` (N, 3)."""
    head = ellipsoid_radius(directions, HEAD_SEMI_AXES)
    for centre, widths, amplitude in FEATURES.values():
        head = head + amplitude * feature_weight(directions, centre, widths)
    head = head + JAW[2] * feature_weight(directions, JAW[0], JAW[1])
    neck = neck_radius(directions)
    p = UNION_SHARPNESS
    return (head**p + neck**p) ** (1.0 / p)


def lat_long_grid(segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closed latitude-longitude sphere with UVs.

    Returns ``directions`` (V, 3) unit, ``faces`` (F, 3), ``uvs`` (T, 2), ``face_uvs`` (F, 3). It has
    ``segments`` longitudes and ``rings = 3 * segments // 4`` latitude rings between the two poles.
    """
    if segments < 8:
        raise ValueError(f"template segments must be >= 8, got {segments}")
    rings = max(3 * segments // 4, 4)
    # Polar angle of the inner rings; denser near the equator where the face is.
    polar = np.pi * (np.arange(1, rings + 1) / (rings + 1))
    lon = 2 * np.pi * np.arange(segments) / segments - np.pi  # -pi is the back seam, 0 is the front
    pp, ll = np.meshgrid(polar, lon, indexing="ij")
    ring_dirs = np.stack([np.sin(pp) * np.sin(ll), np.cos(pp), np.sin(pp) * np.cos(ll)], axis=-1).reshape(
        -1, 3
    )
    directions = np.concatenate([[[0.0, 1.0, 0.0]], ring_dirs, [[0.0, -1.0, 0.0]]])
    top, bottom = 0, 1 + rings * segments

    def vid(r, s):
        return 1 + r * segments + (s % segments)

    # UV vertices: (rings) x (segments + 1) grid (the seam column is duplicated) + one pole UV per segment.
    u_cols = np.arange(segments + 1) / segments
    uv_grid = np.stack(
        np.meshgrid(1.0 - (np.arange(1, rings + 1) / (rings + 1)), u_cols, indexing="ij")[::-1], -1
    )
    uvs = [uv_grid.reshape(-1, 2)]
    n_grid = rings * (segments + 1)
    pole_u = (np.arange(segments) + 0.5) / segments
    uvs.append(np.stack([pole_u, np.ones(segments)], -1))  # top pole UVs
    uvs.append(np.stack([pole_u, np.zeros(segments)], -1))  # bottom pole UVs
    uvs = np.concatenate(uvs)

    def tid(r, s):
        return r * (segments + 1) + s

    faces, face_uvs = [], []
    s = np.arange(segments)
    # Top fan: pole, ring 0 (s+1), ring 0 (s) keeps outward orientation (checked by the tests).
    faces.append(np.stack([np.full(segments, top), vid(0, s + 1), vid(0, s)], -1))
    face_uvs.append(np.stack([n_grid + s, tid(0, s + 1), tid(0, s)], -1))
    for r in range(rings - 1):
        a, b = vid(r, s), vid(r, s + 1)
        c, d = vid(r + 1, s), vid(r + 1, s + 1)
        ta, tb, tc, td = tid(r, s), tid(r, s + 1), tid(r + 1, s), tid(r + 1, s + 1)
        faces += [np.stack([a, b, d], -1), np.stack([a, d, c], -1)]
        face_uvs += [np.stack([ta, tb, td], -1), np.stack([ta, td, tc], -1)]
    last = rings - 1
    faces.append(np.stack([np.full(segments, bottom), vid(last, s), vid(last, s + 1)], -1))
    face_uvs.append(np.stack([n_grid + segments + s, tid(last, s), tid(last, s + 1)], -1))
    faces = np.concatenate(faces).astype(np.int64)
    face_uvs = np.concatenate(face_uvs).astype(np.int64)
    return directions, faces, uvs, face_uvs


def _fix_orientation(vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray):
    """Flip the winding if the mesh's signed volume is negative, so normals point outward."""
    tri = vertices[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if volume < 0:
        return faces[:, ::-1].copy(), face_uvs[:, ::-1].copy()
    return faces, face_uvs


def make_template(segments: int) -> HeadTemplate:
    """Build the template head with ``segments`` longitudes (vertex count ~ 0.75 * segments**2)."""
    directions, faces, uvs, face_uvs = lat_long_grid(segments)
    vertices = directions * template_radius(directions)[:, None]
    faces, face_uvs = _fix_orientation(vertices, faces, face_uvs)
    front = directions[:, 2] > 0.5
    centre_line = np.abs(vertices[:, 0]) < 0.012
    nose_tip = int(
        np.argmax(np.where(front & centre_line & (np.abs(vertices[:, 1]) < 0.04), vertices[:, 2], -np.inf))
    )
    chin_dir = _unit(FEATURES["chin"][0])
    chin = int(np.argmax(directions @ chin_dir))
    ear_height = np.abs(vertices[:, 1] - 0.002) < 0.03
    landmarks = {
        "nose_tip": nose_tip,
        "chin": chin,
        "left_ear": int(np.argmax(np.where(ear_height, vertices[:, 0], -np.inf))),
        "right_ear": int(np.argmin(np.where(ear_height, vertices[:, 0], np.inf))),
        "head_top": int(np.argmax(vertices[:, 1])),
    }
    neck_mask = vertices[:, 1] < NECK_LINE_Y
    return HeadTemplate(vertices, faces, uvs, face_uvs, neck_mask, landmarks)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, uvs=None, face_uvs=None) -> None:
    """Write a triangle mesh as OBJ (1-based indices; ``f v/vt`` when UVs are given)."""
    path = Path(path)
    if (uvs is None) != (face_uvs is None):
        raise ValueError(f"{path}: uvs and face_uvs must be given together")
    lines = ["# relightanyone synthetic head"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    if uvs is not None:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in np.asarray(uvs, dtype=np.float64)]
        for f, t in zip(np.asarray(faces) + 1, np.asarray(face_uvs) + 1, strict=True):
            lines.append(f"f {f[0]}/{t[0]} {f[1]}/{t[1]} {f[2]}/{t[2]}")
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(faces) + 1]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a triangle OBJ. Returns ``vertices (V,3), faces (F,3), uvs (T,2) or None, face_uvs (F,3) or None``."""
    path = Path(path)
    vertices, uvs, faces, face_uvs = [], [], [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if parts[0] == "v":
            vertices.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt":
            uvs.append([float(x) for x in parts[1:3]])
        elif parts[0] == "f":
            if len(parts) != 4:
                raise ValueError(
                    f"{path}:{number}: only triangles are supported, got {len(parts) - 1} corners"
                )
            corners = [p.split("/") for p in parts[1:]]
            faces.append([int(c[0]) - 1 for c in corners])
            if all(len(c) > 1 and c[1] for c in corners):
                face_uvs.append([int(c[1]) - 1 for c in corners])
    if not vertices or not faces:
        raise ValueError(f"{path}: no vertices or faces found")
    if face_uvs and len(face_uvs) != len(faces):
        raise ValueError(f"{path}: some faces have texture indices and some do not")
    return (
        np.array(vertices, dtype=np.float64),
        np.array(faces, dtype=np.int64),
        np.array(uvs, dtype=np.float64) if uvs else None,
        np.array(face_uvs, dtype=np.int64) if face_uvs else None,
    )


def write_template(folder: Path, template: HeadTemplate) -> None:
    """Write ``template.obj``, ``neck_mask.txt`` (one 0/1 per vertex) and ``landmarks.json`` into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_obj(folder / "template.obj", template.vertices, template.faces, template.uvs, template.face_uvs)
    (folder / "neck_mask.txt").write_text("\n".join(str(int(m)) for m in template.neck_mask) + "\n")
    (folder / "landmarks.json").write_text(json.dumps(template.landmarks, indent=1, sort_keys=True))
