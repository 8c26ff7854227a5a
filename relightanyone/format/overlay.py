"""Reprojection overlay: the tracked mesh drawn over stored images, the quickest check that cameras and
meshes agree.

For a row of a normalized dataset, the (subject, frame) mesh of ``meshes.arrow`` is projected with the
row's ``K`` and ``w2c``, and its outline as that camera sees it (silhouette and open boundaries) is drawn in
green (edges of faces below the neck line in orange) over the sRGB preview of the image. An outline that
sits on the head's silhouette means the ingest got the cameras and the canonical space right.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from relightanyone.format.preview import linear_to_srgb_preview
from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.schema import NECK_MASK_NAME, TEMPLATE_NAME
from relightanyone.render.mesh import faces_touching, read_obj

HEAD_COLOUR = (60, 220, 60)  # RGB
NECK_COLOUR = (255, 150, 40)


def project(vertices: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection (the stored images are undistorted): ``(V, 2)`` pixels and ``(V,)`` depths."""
    camera = vertices @ w2c[:3, :3].T + w2c[:3, 3]
    depth = camera[:, 2]
    pixels = (camera[:, :2] / np.maximum(depth, 1e-9)[:, None]) * [K[0, 0], K[1, 1]] + K[:2, 2]
    return pixels, depth


def outline_edges(faces: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Edges where visibility changes: each edge of a visible face that no other visible face shares.

    That is the silhouette (a visible face next to a back-facing one) and the open boundaries (the neck's
    cut), a few hundred edges whatever the mesh density, where drawing every face's edges paints the whole
    head solid at real densities (7k-60k vertices over 512² pixels).

    Args:
        faces: ``(F, 3)`` vertex indices; visible: ``(F,)`` bool.
    Returns:
        ``(E, 3)`` int64: the two vertex indices of each outline edge and the visible face it belongs to.
    """
    chosen = np.flatnonzero(visible)
    corners = faces[chosen]
    edges = np.sort(np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]], corners[:, [2, 0]]]), axis=1)
    owners = np.tile(chosen, 3)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    single = counts[inverse.reshape(-1)] == 1
    return np.column_stack([edges[single], owners[single]]).astype(np.int64)


def draw_mesh_over(
    image_srgb: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    neck_faces: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    scale: int = 4,
) -> np.ndarray:
    """Draw the outline of the mesh as the camera sees it (silhouette and open boundaries) over an image.

    Only the outline is drawn, so the image stays readable inside it at any mesh density; edges of neck
    faces are drawn in the neck colour, so the neck line shows where the outline changes colour.

    Args:
        image_srgb: ``(H, W, 3)`` uint8 RGB preview; vertices ``(V, 3)`` canonical; faces ``(F, 3)``;
        neck_faces ``(F,)`` bool; K ``(3, 3)`` and w2c ``(4, 4)`` of the stored image.
        scale: the drawing is made ``scale``× larger so thin edges stay readable on small crops.
    Returns:
        ``(scale·H, scale·W, 3)`` uint8 RGB.
    """
    import cv2

    height, width = image_srgb.shape[:2]
    canvas = cv2.resize(image_srgb, (width * scale, height * scale), interpolation=cv2.INTER_NEAREST)
    pixels, depth = project(vertices, K, w2c)
    camera = vertices @ w2c[:3, :3].T + w2c[:3, 3]
    corners = camera[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    # Outward-wound faces (the template's convention) whose normal points back to the camera are visible.
    visible = (np.einsum("fk,fk->f", normals, corners.mean(axis=1)) < 0) & (depth[faces] > 0).all(axis=1)
    edges = outline_edges(faces, visible)
    shift = 4  # cv2 fixed-point bits for sub-pixel line ends
    points = np.round((pixels + 0.5) * scale * (1 << shift)).astype(np.int32)
    for is_neck, colour in ((True, NECK_COLOUR), (False, HEAD_COLOUR)):
        chosen = edges[neck_faces[edges[:, 2]] == is_neck]
        if len(chosen):
            cv2.polylines(canvas, list(points[chosen[:, :2]]), False, colour, 1, cv2.LINE_AA, shift)
    return canvas


def reprojection_overlays(
    dataset_dir: Path, keys: list[str] | None = None, samples: int = 8
) -> list[np.ndarray]:
    """Overlays for ``keys`` (default: ``samples`` keys spread over the dataset) of a normalized dataset
    written by ingest (it holds ``meshes.arrow`` and ``template.obj``). Returns ``(H', W', 3)`` uint8 RGB."""

    dataset_dir = Path(dataset_dir)
    template_path = dataset_dir / TEMPLATE_NAME
    if not template_path.is_file():
        raise FileNotFoundError(
            f"{template_path} is missing: only datasets written by ingest can be overlaid"
        )
    vertices_template, faces = read_obj(template_path)
    neck_path = dataset_dir / NECK_MASK_NAME
    neck_vertices = (
        np.loadtxt(neck_path, ndmin=1) > 0.5
        if neck_path.is_file()
        else np.zeros(len(vertices_template), bool)
    )
    neck_faces = faces_touching(neck_vertices, faces)
    dataset = NormalizedDataset(dataset_dir)
    meshes = dataset.meshes()
    if keys is None:
        all_keys = dataset.keys
        picks = np.linspace(0, len(all_keys) - 1, min(samples, len(all_keys))).astype(int)
        keys = [all_keys[i] for i in sorted(set(picks.tolist()))]
    overlays = []
    for key in keys:
        row, image, _ = dataset.decoded(key)
        mesh_key = f"{row.subject}/{row.frame:06d}"
        if mesh_key not in meshes:
            raise KeyError(f"{dataset_dir}: no mesh for {mesh_key} in meshes.arrow")
        vertices = np.asarray(meshes[mesh_key], dtype=np.float64).reshape(-1, 3)
        preview = linear_to_srgb_preview(image)
        overlays.append(draw_mesh_over(preview, vertices, faces, neck_faces, row.K, row.w2c))
    return overlays
