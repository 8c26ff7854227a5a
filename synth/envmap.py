"""Environment maps for image-based relighting answers, and EXR input/output.

Lat-long (equirectangular) maps of linear HDR radiance, +y up. Pixel (row i, column j) of an
(h, w) map covers polar angles ``[i, i + 1] * pi / h`` from +y and longitudes
``[j, j + 1] * 2 pi / w - pi``, where longitude phi gives the direction
``(sin(theta) sin(phi), cos(theta), sin(theta) cos(phi))``. So the horizontal centre of the map
(u = 0.5, the border between columns w/2 - 1 and w/2) faces +z, the subject's front; column 3/4 of the
way across faces +x (the subject's left) and the left and right edges face -z (behind the head).

Image-based relighting (the 3DPR protocol): each light of an OLAT rig owns the Voronoi cell of its
direction on the sphere; its weight is the map's radiance integrated over that cell
(``sum radiance * solid angle``, an irradiance-like quantity per RGB channel). An OLAT image taken with
a light of intensity I at distance d from the head gives the head irradiance ``I / d^2``; dividing the
cell integral by that, as :func:`olat_relight_weights` does, makes ``relit = sum_k w_k * olat_k`` the
image under the environment treated as infinitely far away.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

ENVMAP_SHAPE = (10, 20)  # (h, w), as in the 3DPR evaluation maps


def latlong_directions(height: int, width: int, subsamples: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Directions and solid angles of a lat-long map's (sub-)pixels.

    Returns ``directions (h, w, s*s, 3)`` unit vectors and ``solid_angles (h, w, s*s)`` (steradians,
    summing to 4 pi), where each pixel is split into s x s equal-angle sub-pixels.
    """
    s = int(subsamples)
    rows = height * s
    cols = width * s
    theta_edges = np.linspace(0.0, np.pi, rows + 1)
    theta = 0.5 * (theta_edges[:-1] + theta_edges[1:])
    phi = (np.arange(cols) + 0.5) / cols * 2 * np.pi - np.pi
    band = (np.cos(theta_edges[:-1]) - np.cos(theta_edges[1:])) * (2 * np.pi / cols)  # (rows,)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(tt) * np.sin(pp), np.cos(tt), np.sin(tt) * np.cos(pp)], axis=-1)
    omega = np.broadcast_to(band[:, None], (rows, cols))
    dirs = dirs.reshape(height, s, width, s, 3).transpose(0, 2, 1, 3, 4).reshape(height, width, s * s, 3)
    omega = omega.reshape(height, s, width, s).transpose(0, 2, 1, 3).reshape(height, width, s * s)
    return dirs, np.ascontiguousarray(omega)


def procedural_envmaps(count: int, seed: int) -> list[tuple[str, np.ndarray]]:
    """``count`` deterministic (10, 20, 3) float32 lat-long maps named ``env_000``, ``env_001`` ...

    Each is a sky-to-ground gradient with coloured low-frequency variation and one to three bright
    area sources (sun, windows, lamps), so relit images have clear directional light and colour.
    """
    if count < 0:
        raise ValueError(f"envmap count must be >= 0, got {count}")
    rng = np.random.default_rng(seed)
    h, w = ENVMAP_SHAPE
    dirs, _ = latlong_directions(h, w, 1)
    dirs = dirs[:, :, 0]
    maps = []
    for index in range(count):
        sky = rng.uniform(0.1, 0.6, size=3) * np.array([0.7, 0.85, 1.0])
        ground = rng.uniform(0.05, 0.3, size=3) * np.array([1.0, 0.85, 0.7])
        up = np.clip(dirs[..., 1:2], -1, 1)
        radiance = np.where(up > 0, sky * (0.6 + 0.4 * up), ground * (0.6 - 0.4 * up))
        for _ in range(3):
            centre = rng.normal(size=3)
            centre /= np.linalg.norm(centre)
            tint = rng.uniform(0.6, 1.4, size=3)
            radiance = radiance * (1 + 0.3 * tint * np.exp((dirs @ centre - 1) / 0.5)[..., None])
        for _ in range(int(rng.integers(1, 4))):
            centre = rng.normal(size=3)
            centre[1] = abs(centre[1]) * 0.8  # sources mostly above the horizon
            centre /= np.linalg.norm(centre)
            colour = rng.uniform(0.5, 1.0, size=3)
            power = rng.uniform(3.0, 20.0)
            width = rng.uniform(0.05, 0.2)
            radiance = radiance + power * colour * np.exp((dirs @ centre - 1) / width)[..., None]
        maps.append((f"env_{index:03d}", radiance.astype(np.float32)))
    return maps


def envmap_light_weights(envmap: np.ndarray, light_directions: np.ndarray, subsamples: int = 8) -> np.ndarray:
    """(L, 3) radiance x solid angle of ``envmap`` (h, w, 3) over the Voronoi cell of each light.

    ``light_directions`` (L, 3) are unit vectors in canonical space (from the head toward each light).
    Each map pixel is split into ``subsamples`` x ``subsamples`` sub-pixels (the map is piecewise
    constant) and every sub-pixel goes to the light with the nearest direction. The weights sum to the
    map's total ``sum radiance * solid angle`` over the sphere.
    """
    env = np.asarray(envmap, dtype=np.float64)
    if env.ndim != 3 or env.shape[2] != 3:
        raise ValueError(f"envmap must be (h, w, 3), got {env.shape}")
    lights = np.asarray(light_directions, dtype=np.float64).reshape(-1, 3)
    if len(lights) == 0:
        raise ValueError("envmap_light_weights needs at least one light direction")
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    h, w, _ = env.shape
    dirs, omega = latlong_directions(h, w, subsamples)
    nearest = np.argmax(dirs.reshape(-1, 3) @ lights.T, axis=1)  # (h*w*s*s,)
    contribution = (env[:, :, None, :] * omega[..., None]).reshape(-1, 3)
    weights = np.zeros((len(lights), 3))
    for channel in range(3):
        weights[:, channel] = np.bincount(nearest, weights=contribution[:, channel], minlength=len(lights))
    return weights


def olat_relight_weights(
    envmap: np.ndarray, light_positions: np.ndarray, light_intensities: np.ndarray, centre=(0.0, 0.0, 0.0)
) -> np.ndarray:
    """(L, 3) weights with ``relit = sum_k w[k] * olat_image[k]`` for OLAT images of these point lights.

    The Voronoi cell integrals of :func:`envmap_light_weights` (directions seen from ``centre``, the head
    centre in canonical metres) divided by each light's irradiance at the centre, ``I_k / d_k^2``.
    """
    positions = np.asarray(light_positions, dtype=np.float64).reshape(-1, 3) - np.asarray(
        centre, dtype=np.float64
    )
    intensities = np.asarray(light_intensities, dtype=np.float64).reshape(-1, 3)
    if np.any(intensities <= 0):
        raise ValueError("olat_relight_weights needs strictly positive light intensities")
    dist2 = (positions**2).sum(axis=1, keepdims=True)
    cell = envmap_light_weights(envmap, positions / np.sqrt(dist2))
    return cell / (intensities / dist2)


EXR_COMPRESSIONS = {
    "zip": OpenEXR.ZIP_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
    "none": OpenEXR.NO_COMPRESSION,
}


def write_exr(path: Path, image: np.ndarray, half: bool = False, compression: str = "zip") -> None:
    """Write an (H, W, 3) linear RGB image as a scanline EXR (FLOAT, or HALF if ``half``).

    ``compression`` is one of "zip" (smallest), "rle" (about twice as fast to write), "piz", "none".
    The header carries no dates, so equal pixels give equal bytes.
    """
    if compression not in EXR_COMPRESSIONS:
        raise ValueError(
            f"{path}: unknown EXR compression {compression!r}; expected one of {', '.join(EXR_COMPRESSIONS)}"
        )
    path = Path(path)
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{path}: write_exr expects an (H, W, 3) image, got {img.shape}")
    dtype = np.float16 if half else np.float32
    planar = np.ascontiguousarray(np.moveaxis(img, -1, 0), dtype=dtype)  # one copy into (3, H, W)
    channels = {c: planar[i] for i, c in enumerate("RGB")}
    header = {"compression": EXR_COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    path.parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def read_exr(path: Path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB from an EXR with R, G, B channels (FLOAT or HALF)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such EXR file")
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = exr.channels()
        missing = [c for c in "RGB" if c not in channels]
        if missing:
            raise ValueError(
                f"{path}: EXR lacks channel(s) {', '.join(missing)}; found {', '.join(sorted(channels))}"
            )
        return np.stack([channels[c].pixels.astype(np.float32) for c in "RGB"], axis=-1)
