"""Ground-truth ray tracer of the synthetic world (trimesh + embree, no rasterization).

Conventions:

* Geometry in canonical head space (metres). Cameras are OpenCV pinholes with OpenCV distortion
  ``(k1, k2, p1, p2, k3)``; ``K`` is in pixels of the written image and the centre of pixel (u, v) is
  at (u, v). One primary ray goes through the centre of each pixel of the *distorted* image (pixel
  centres are undistorted with OpenCV), so a 3-D point X is drawn where ``cv2.projectPoints`` puts it.
  With ``supersampling = s`` each pixel is traced at s x s evenly spaced sub-pixel positions and averaged.
* Lights are isotropic point lights: ``intensities`` are radiant intensities (linear RGB, W/sr-like
  units); a surface at distance d receives irradiance ``I cos(theta) / d^2``.
* Shading is reflected radiance ``L = (albedo / pi + f_spec) * I * cos(theta) / d^2`` summed over lights,
  with hard shadows from shadow rays. ``f_spec`` is a white, energy-normalized Blinn-Phong lobe
  ``ks * (e + 8) / (8 pi) * max(n.h, 0)^e`` whose exponent comes from the roughness map r:
  ``alpha = r^2, e = 2 / alpha^2 - 2`` (the usual Beckmann-to-Phong match).
* Every light is shaded independently and the full image is the sum of the per-light images, so
  "full-on" equals the sum of the OLAT images up to float rounding.
* Textures are UV maps with row 0 at v = 1, sampled bilinearly (clamped at the borders).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

SHADOW_EPSILON = 1e-4  # metres: shadow rays start this far off the surface to avoid self-hits
PAIRS_PER_BATCH = 300_000  # (light, hit) pairs shaded at once: small enough to stay in cache
_RAY_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
_RAY_CACHE_SIZE = 64
_RAY_CACHE_MAX_RAYS = 1_000_000


@dataclass
class SynthCamera:
    """OpenCV camera: ``w2c`` maps canonical metres to camera coordinates (x right, y down, z forward)."""

    name: str
    K: np.ndarray  # (3, 3)
    w2c: np.ndarray  # (4, 4)
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # (5,) k1, k2, p1, p2, k3

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float64)
        self.w2c = np.asarray(self.w2c, dtype=np.float64)
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.K.shape != (3, 3) or self.w2c.shape != (4, 4):
            raise ValueError(
                f"camera {self.name}: K must be (3, 3) and w2c (4, 4), got {self.K.shape}, {self.w2c.shape}"
            )
        if len(self.dist) not in (4, 5, 8, 12, 14):
            raise ValueError(
                f"camera {self.name}: dist needs 4, 5, 8, 12 or 14 OpenCV coefficients, got {len(self.dist)}"
            )
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(
                f"camera {self.name}: image size must be positive, got {self.width}x{self.height}"
            )

    @property
    def c2w(self) -> np.ndarray:
        """(4, 4) camera-to-canonical rigid transform."""
        return np.linalg.inv(self.w2c)

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in canonical space."""
        return self.c2w[:3, 3]

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) pixel positions of canonical ``points`` (N, 3) with distortion (``cv2.projectPoints``)."""
        rvec, _ = cv2.Rodrigues(np.ascontiguousarray(self.w2c[:3, :3], dtype=np.float64))
        uv, _ = cv2.projectPoints(
            np.asarray(points, dtype=np.float64).reshape(-1, 1, 3),
            rvec,
            self.w2c[:3, 3].astype(np.float64),
            np.asarray(self.K, dtype=np.float64),
            np.asarray(self.dist, dtype=np.float64),
        )
        return uv.reshape(-1, 2)

    def pixel_rays(self, supersampling: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays ``origins, directions`` (H*s * W*s, 3); cached, since rigs reuse their cameras."""
        key = (
            np.asarray(self.K, np.float64).tobytes(),
            np.asarray(self.w2c, np.float64).tobytes(),
            np.asarray(self.dist, np.float64).tobytes(),
            int(self.width),
            int(self.height),
            int(supersampling),
        )
        if key not in _RAY_CACHE:
            origins, directions = self._compute_pixel_rays(supersampling)
            if len(origins) > _RAY_CACHE_MAX_RAYS:  # big images: recompute rather than hold memory
                return origins, directions
            if len(_RAY_CACHE) >= _RAY_CACHE_SIZE:
                _RAY_CACHE.pop(next(iter(_RAY_CACHE)))  # drop the oldest entry
            origins.flags.writeable = False
            directions.flags.writeable = False
            _RAY_CACHE[key] = (origins, directions)
        return _RAY_CACHE[key]

    def _compute_pixel_rays(self, supersampling: int) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays ``origins, directions`` (H*s * W*s, 3), row-major over the sub-pixel grid.

        Sub-pixel (row i, col j) of pixel (u, v) sits at ``u + (j + 0.5) / s - 0.5`` (same for v), so
        with s = 1 the ray goes through the pixel centre.
        """
        s = int(supersampling)
        if s < 1:
            raise ValueError(f"supersampling must be >= 1, got {supersampling}")
        offsets = (np.arange(s) + 0.5) / s - 0.5
        xs = (np.arange(self.width)[:, None] + offsets[None, :]).reshape(-1)
        ys = (np.arange(self.height)[:, None] + offsets[None, :]).reshape(-1)
        grid_x, grid_y = np.meshgrid(xs, ys)
        pixels = np.stack([grid_x, grid_y], axis=-1).reshape(-1, 1, 2).astype(np.float64)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        normalized = cv2.undistortPoints(
            pixels,
            np.asarray(self.K, dtype=np.float64),
            np.asarray(self.dist, dtype=np.float64),
            criteria=criteria,
        ).reshape(-1, 2)
        directions_cam = np.concatenate([normalized, np.ones((len(normalized), 1))], axis=1)
        c2w = self.c2w
        directions = directions_cam @ c2w[:3, :3].T
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        origins = np.ascontiguousarray(np.broadcast_to(c2w[:3, 3], directions.shape))
        return origins, directions


@dataclass
class PointLights:
    """Isotropic point lights in canonical space."""

    positions: np.ndarray  # (L, 3) metres
    intensities: np.ndarray  # (L, 3) linear RGB radiant intensity

    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        self.intensities = np.asarray(self.intensities, dtype=np.float64).reshape(-1, 3)
        if len(self.positions) != len(self.intensities):
            raise ValueError(f"{len(self.positions)} light positions but {len(self.intensities)} intensities")

    def __len__(self) -> int:
        return len(self.positions)

    def subset(self, indices) -> PointLights:
        """The lights at ``indices`` (in that order)."""
        idx = np.asarray(indices, dtype=np.int64)
        return PointLights(self.positions[idx], self.intensities[idx])

    def transformed(self, matrix: np.ndarray) -> PointLights:
        """Lights moved by a (4, 4) rigid ``matrix`` (e.g. into a head's frame)."""
        m = np.asarray(matrix, dtype=np.float64)
        return PointLights(self.positions @ m[:3, :3].T + m[:3, 3], self.intensities.copy())


@dataclass
class Scene:
    """A textured triangle mesh plus optional extra textured meshes (chart, background plate ...).

    The first mesh is the head: ``RenderResult.mask`` is its silhouette. Scalar maps may be (S, S) or
    (1, 1) for a constant; ``albedo`` is (S, S, 3) linear RGB.
    """

    vertices: np.ndarray  # (V, 3) metres
    faces: np.ndarray  # (F, 3) int
    uvs: np.ndarray  # (T, 2) in [0, 1]
    face_uvs: np.ndarray  # (F, 3) int into uvs
    albedo: np.ndarray  # (S, S, 3) float32 linear
    specular_intensity: np.ndarray  # (S, S) float32
    roughness: np.ndarray  # (S, S) float32
    extras: list[Scene] = field(default_factory=list)

    @classmethod
    def from_subject(cls, template, subject, head_pose: np.ndarray | None = None) -> Scene:
        """The subject's head on the template topology, moved by ``head_pose`` (4, 4) if given."""
        vertices = np.asarray(subject.vertices, dtype=np.float64)
        if head_pose is not None:
            pose = np.asarray(head_pose, dtype=np.float64)
            vertices = vertices @ pose[:3, :3].T + pose[:3, 3]
        return cls(
            vertices,
            template.faces,
            template.uvs,
            template.face_uvs,
            subject.albedo,
            subject.specular_intensity,
            subject.roughness,
        )

    def merge(self, other: Scene) -> Scene:
        """A new scene with ``other`` (and its own extras) added after this scene's meshes."""
        return replace(self, extras=[*self.extras, *other.meshes()])

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_traced", None)  # the embree structure is rebuilt on demand, never pickled
        return state

    def meshes(self) -> list[Scene]:
        """This scene's meshes in render order, each without extras."""
        return [replace(self, extras=[]), *(m for extra in self.extras for m in extra.meshes())]


def textured_quad(
    corners: np.ndarray, albedo: np.ndarray, specular_intensity: float = 0.0, roughness: float = 1.0
) -> Scene:
    """A two-triangle plane with corners (4, 3) in order top-left, top-right, bottom-right, bottom-left.

    ``albedo`` (S, S, 3) or (3,) maps with row 0 along the top edge. Its front side is the one from
    which the corners appear clockwise, i.e. the normal is (top-right - top-left) x (bottom-left - top-left).
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(4, 3)
    albedo = np.asarray(albedo, dtype=np.float32)
    if albedo.ndim == 1:
        albedo = albedo.reshape(1, 1, 3)
    faces = np.array([[0, 3, 2], [0, 2, 1]], dtype=np.int64)
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    return Scene(
        corners,
        faces,
        uvs,
        faces.copy(),
        albedo,
        np.full((1, 1), specular_intensity, np.float32),
        np.full((1, 1), roughness, np.float32),
    )


@dataclass
class RenderResult:
    image: np.ndarray  # (H, W, 3) float32 linear HDR, or (L, H, W, 3) with per_light
    mask: np.ndarray  # (H, W) bool: pixel centre sees the first mesh (the head)
    triangle_id: np.ndarray  # (H, W) int64 into the merged faces (head first), -1 = miss
    depth: np.ndarray  # (H, W) float32 camera z (OpenCV) of the hit, 0 = miss


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``texture`` (S, S, C) or (S, S) at ``uv`` (N, 2); returns (N, C) or (N,).

    Texel (row i, col j) has its centre at ``u = (j + 0.5) / S``, ``v = 1 - (i + 0.5) / S``.
    """
    tex = np.asarray(texture)
    h, w = tex.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 1)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    if tex.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_n)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-20)


class _TracedScene:
    """The merged geometry of a scene, its embree acceleration structure and per-face lookups."""

    def __init__(self, scene: Scene):
        self.meshes = scene.meshes()
        offsets, vertices, faces, normals = [0], [], [], []
        base = 0
        for mesh in self.meshes:
            v = np.asarray(mesh.vertices, dtype=np.float64)
            f = np.asarray(mesh.faces, dtype=np.int64)
            if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
                raise ValueError(f"scene mesh faces must be (F, 3) with F > 0, got {f.shape}")
            if f.min() < 0 or f.max() >= len(v):
                raise ValueError(
                    f"scene mesh faces index vertex {f.max()} but the mesh has {len(v)} vertices"
                )
            if np.asarray(mesh.face_uvs).shape != f.shape:
                raise ValueError(
                    f"scene mesh face_uvs must match faces {f.shape}, got {np.asarray(mesh.face_uvs).shape}"
                )
            if np.asarray(mesh.albedo).ndim != 3 or np.asarray(mesh.albedo).shape[2] != 3:
                raise ValueError(f"scene mesh albedo must be (S, S, 3), got {np.asarray(mesh.albedo).shape}")
            vertices.append(v)
            faces.append(f + base)
            normals.append(vertex_normals(v, f))
            base += len(v)
            offsets.append(offsets[-1] + len(f))
        self.face_offsets = np.array(offsets)
        self.vertices = np.concatenate(vertices)
        self.faces = np.concatenate(faces)
        self.normals = np.concatenate(normals)
        self.embree = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self.embree, vertices=self.vertices[self.faces].astype(np.float32))

    def first_hits(
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest hits: ``triangle (N,) int64 (-1 miss), barycentric u (N,), v (N,)`` (embree's (1-u-v, u, v))."""
        result = self.embree.run(
            np.ascontiguousarray(origins, dtype=np.float32),
            np.ascontiguousarray(directions, dtype=np.float32),
            output=1,
        )
        return (
            result["primID"].astype(np.int64),
            result["u"].astype(np.float64),
            result["v"].astype(np.float64),
        )

    def occluded(self, origins: np.ndarray, directions: np.ndarray, max_distance: np.ndarray) -> np.ndarray:
        """(N,) bool: something lies along each ray closer than ``max_distance``."""
        hits = self.embree.run(
            np.ascontiguousarray(origins, dtype=np.float32),
            np.ascontiguousarray(directions, dtype=np.float32),
            dists=np.ascontiguousarray(max_distance, dtype=np.float32),
            query="OCCLUDED",
        )
        return hits != -1


def _traced(scene: Scene) -> _TracedScene:
    """The scene's acceleration structure, built on first use and kept on the scene.

    A scene is treated as immutable once rendered (rigs render one scene from many cameras).
    """
    traced = scene.__dict__.get("_traced")
    if traced is None:
        traced = _TracedScene(scene)
        scene.__dict__["_traced"] = traced
    return traced


@dataclass
class _SurfaceHits:
    """Shading inputs at N primary-ray hits."""

    points: np.ndarray  # (N, 3) float64
    geometric_normals: np.ndarray  # (N, 3) facing the viewer
    shading_normals: np.ndarray  # (N, 3)
    view: np.ndarray  # (N, 3) unit vector toward the viewer
    albedo: np.ndarray  # (N, 3) float32
    specular: np.ndarray  # (N,) float32
    roughness: np.ndarray  # (N,) float32


def _surface_hits(
    traced: _TracedScene, triangle: np.ndarray, bu: np.ndarray, bv: np.ndarray, directions
) -> _SurfaceHits:
    faces = traced.faces[triangle]
    w0 = (1.0 - bu - bv)[:, None]
    corners = traced.vertices[faces]  # (N, 3, 3)
    points = w0 * corners[:, 0] + bu[:, None] * corners[:, 1] + bv[:, None] * corners[:, 2]
    geo = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    geo /= np.maximum(np.linalg.norm(geo, axis=1, keepdims=True), 1e-30)
    n = traced.normals[faces]
    shading = w0 * n[:, 0] + bu[:, None] * n[:, 1] + bv[:, None] * n[:, 2]
    shading /= np.maximum(np.linalg.norm(shading, axis=1, keepdims=True), 1e-30)
    facing = np.where(np.einsum("ij,ij->i", geo, directions) > 0, -1.0, 1.0)[:, None]
    geo *= facing
    shading *= facing

    albedo = np.empty((len(triangle), 3), np.float32)
    specular = np.empty(len(triangle), np.float32)
    roughness = np.empty(len(triangle), np.float32)
    mesh_of_hit = np.searchsorted(traced.face_offsets, triangle, side="right") - 1
    for index, mesh in enumerate(traced.meshes):
        sel = np.nonzero(mesh_of_hit == index)[0]
        if len(sel) == 0:
            continue
        local = triangle[sel] - traced.face_offsets[index]
        tuv = np.asarray(mesh.uvs, dtype=np.float64)[np.asarray(mesh.face_uvs)[local]]  # (n, 3, 2)
        uv = (
            (1.0 - bu[sel] - bv[sel])[:, None] * tuv[:, 0]
            + bu[sel, None] * tuv[:, 1]
            + bv[sel, None] * tuv[:, 2]
        )
        albedo[sel] = sample_texture(np.asarray(mesh.albedo, np.float32), uv)
        specular[sel] = sample_texture(np.asarray(mesh.specular_intensity, np.float32), uv)
        roughness[sel] = sample_texture(np.asarray(mesh.roughness, np.float32), uv)
    return _SurfaceHits(points, geo, shading, -directions, albedo, specular, np.clip(roughness, 0.02, 1.0))


def shade_point_lights(traced: _TracedScene, hits: _SurfaceHits, lights: PointLights) -> np.ndarray:
    """(L, N, 3) float32 reflected radiance of each hit under each light alone, with shadows.

    Works on (lights, hits) planes of float32 coordinates, one plane per axis, which numpy handles far
    faster than (lights, hits, 3) arrays.
    """
    n_hits, n_lights = len(hits.points), len(lights)
    out = np.zeros((n_lights, n_hits, 3), np.float32)
    if n_hits == 0 or n_lights == 0:
        return out
    f32 = np.float32

    def planes(a):  # (N, 3) -> three contiguous (1, N) float32 rows
        a = np.ascontiguousarray(np.asarray(a, dtype=f32).T)
        return a[0][None], a[1][None], a[2][None]

    alpha2 = hits.roughness.astype(f32) ** 4  # alpha = roughness^2
    exponent = (f32(2.0) / np.maximum(alpha2, f32(1e-8)) - f32(2.0))[None]
    lobe_norm = (hits.specular.astype(f32) * (exponent[0] + f32(8.0)) / f32(8.0 * np.pi))[None]
    diffuse = np.asarray(hits.albedo, dtype=f32) / f32(np.pi)
    px, py, pz = planes(hits.points)
    gx, gy, gz = planes(hits.geometric_normals)
    sx, sy, sz = planes(hits.shading_normals)
    vx, vy, vz = planes(hits.view)
    origins = (hits.points + SHADOW_EPSILON * hits.geometric_normals).astype(f32)
    chunk = max(1, PAIRS_PER_BATCH // n_hits)
    for start in range(0, n_lights, chunk):
        stop = min(start + chunk, n_lights)
        pos = lights.positions[start:stop].astype(f32)
        lx, ly, lz = pos[:, 0:1] - px, pos[:, 1:2] - py, pos[:, 2:3] - pz  # (C, N) toward the light
        dist2 = lx * lx + ly * ly + lz * lz
        inv_dist = f32(1.0) / np.sqrt(dist2)
        lx *= inv_dist
        ly *= inv_dist
        lz *= inv_dist
        cos_shade = lx * sx + ly * sy + lz * sz
        lit = (lx * gx + ly * gy + lz * gz > 0) & (cos_shade > 0)
        # Shadow rays only where the light is above the surface.
        shadow_origins = np.broadcast_to(origins[None], (stop - start, n_hits, 3))[lit]
        shadow_dirs = np.stack([lx[lit], ly[lit], lz[lit]], axis=1)
        length = f32(1.0) / inv_dist[lit] - f32(2 * SHADOW_EPSILON)
        lit[lit] = ~traced.occluded(shadow_origins, shadow_dirs, length)
        lx += vx  # half vectors (unnormalized)
        ly += vy
        lz += vz
        n_dot_h = (lx * sx + ly * sy + lz * sz) / np.maximum(np.sqrt(lx * lx + ly * ly + lz * lz), f32(1e-20))
        np.clip(n_dot_h, f32(0.0), f32(1.0), out=n_dot_h)
        spec = lobe_norm * np.power(n_dot_h, exponent)  # (C, N)
        irradiance = np.where(lit, cos_shade / dist2, f32(0.0))  # (C, N)
        intensity = lights.intensities[start:stop].astype(f32)
        for channel in range(3):
            out[start:stop, :, channel] = (diffuse[None, :, channel] + spec) * (
                irradiance * intensity[:, channel : channel + 1]
            )
    return out


def _background_pixels(background, height: int, width: int, s: int) -> np.ndarray | None:
    """(H*s * W*s, 3) background radiance per primary ray, or None."""
    if background is None:
        return None
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape == (3,):
        return np.broadcast_to(bg, (height * s * width * s, 3))
    if bg.shape != (height, width, 3):
        raise ValueError(f"background must be (3,) or ({height}, {width}, 3), got {bg.shape}")
    return np.repeat(np.repeat(bg, s, axis=0), s, axis=1).reshape(-1, 3)


def render(
    scene: Scene,
    camera: SynthCamera,
    lights: PointLights,
    *,
    per_light: bool = False,
    background=None,
    supersampling: int = 1,
) -> RenderResult:
    """Ray trace ``scene`` seen by ``camera`` under point ``lights``.

    ``background`` ((3,) or (H, W, 3) linear radiance) fills the pixels whose rays hit nothing; it only
    applies to the combined image, so it cannot be combined with ``per_light``. Returns
    :class:`RenderResult` (image (H, W, 3), or (L, H, W, 3) with ``per_light``).
    """
    if per_light and background is not None:
        raise ValueError("background applies to the combined image only; render per_light without it")
    traced = _traced(scene)
    h, w, s = int(camera.height), int(camera.width), int(supersampling)

    # Identification buffers (triangle id, mask, depth) come from the pixel-centre rays.
    centre_origins, centre_directions = camera.pixel_rays(1)
    triangle, cu, cv_ = traced.first_hits(centre_origins, centre_directions)
    hit = np.nonzero(triangle >= 0)[0]
    triangle_id = triangle.reshape(h, w)
    mask = ((triangle >= 0) & (triangle < traced.face_offsets[1])).reshape(h, w)
    centre_surface = _surface_hits(traced, triangle[hit], cu[hit], cv_[hit], centre_directions[hit])
    depth = np.zeros(h * w, np.float32)
    depth[hit] = (centre_surface.points @ camera.w2c[:3, :3].T + camera.w2c[:3, 3])[:, 2]

    if s == 1:
        sample_hit, surface = hit, centre_surface
    else:
        origins, directions = camera.pixel_rays(s)
        sample_triangle, bu, bv = traced.first_hits(origins, directions)
        sample_hit = np.nonzero(sample_triangle >= 0)[0]
        surface = _surface_hits(
            traced, sample_triangle[sample_hit], bu[sample_hit], bv[sample_hit], directions[sample_hit]
        )

    radiance = shade_point_lights(traced, surface, lights)  # (L, n, 3)
    n_samples = h * s * w * s
    if per_light:
        samples = np.zeros((len(lights), n_samples, 3), np.float32)
        for light in range(len(lights)):  # row scatter per light is much faster than one 3-D scatter
            samples[light, sample_hit] = radiance[light]
        image = samples.reshape(len(lights), h, s, w, s, 3)
        image = (
            image[:, :, 0, :, 0] if s == 1 else image.mean(axis=(2, 4), dtype=np.float64).astype(np.float32)
        )
    else:
        samples = np.zeros((n_samples, 3), np.float32)
        samples[sample_hit] = radiance.sum(axis=0, dtype=np.float64)
        bg = _background_pixels(background, h, w, s)
        if bg is not None:
            missed = np.ones(n_samples, bool)
            missed[sample_hit] = False
            samples[missed] = bg[missed]
        image = samples.reshape(h, s, w, s, 3)
        image = image[:, 0, :, 0] if s == 1 else image.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
    return RenderResult(image=image, mask=mask, triangle_id=triangle_id, depth=depth.reshape(h, w))
