"""A plausible RGB picture of the ray-cast camera view: sun, shadows, sky, simple textures.

The RGB image is what an image segmenter and a person looking at overlays see; it does not have to
be photo-real, but it should not be a flat label colouring either: Lambert shading with cast
shadows, a sky gradient, haze, procedural grain and facade windows give surfaces the cues a
segmentation network keys on.
"""

from __future__ import annotations

import numpy as np

from semcal_tools.scenes.props import BUILDING, LANE_MARKING, ROAD, SIDEWALK, TERRAIN, VEGETATION
from semcal_tools.scenes.mesh import LabelledMesh
from semcal_tools.scenes.sensors import Hits, World

HORIZON = np.array([0.78, 0.84, 0.90])
ZENITH = np.array([0.30, 0.50, 0.82])


def _hash(cells: np.ndarray) -> np.ndarray:
    """A repeatable pseudo-random value in [0, 1) per integer 3-D cell."""
    c = cells.astype(np.int64)
    h = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / 65536.0


def texture(points: np.ndarray, normals: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Brightness factors (N,) and a window mask (N,) from world position and class."""
    grain = 0.85 + 0.3 * _hash(np.floor(points / 0.07))
    coarse = 0.9 + 0.2 * _hash(np.floor(points / 1.3))
    factor = np.ones(len(points), np.float32)
    flat = (labels == ROAD) | (labels == SIDEWALK) | (labels == LANE_MARKING)
    factor[flat] = (grain * coarse)[flat]
    green = (labels == TERRAIN) | (labels == VEGETATION)
    factor[green] = (0.75 + 0.5 * _hash(np.floor(points / 0.25)))[green] * coarse[green]
    tiles = labels == SIDEWALK
    if tiles.any():  # paving joints
        frac = np.abs(((points[tiles, :2] / 0.6) % 1.0) - 0.5)
        factor[tiles] *= np.where(frac.max(1) > 0.46, 0.8, 1.0)
    window = np.zeros(len(points), bool)
    wall = (labels == BUILDING) & (np.abs(normals[:, 2]) < 0.5)
    if wall.any():
        n = normals[wall]
        along = points[wall, 0] * -n[:, 1] + points[wall, 1] * n[:, 0]
        u = (along / 3.0) % 1.0
        v = (points[wall, 2] / 3.2) % 1.0
        window[wall] = (u > 0.25) & (u < 0.75) & (v > 0.3) & (v < 0.8) & (points[wall, 2] > 2.6)
    return factor, window


def sky(directions: np.ndarray) -> np.ndarray:
    up = np.clip(directions[:, 2], 0.0, 1.0)[:, None] ** 0.6
    return HORIZON * (1 - up) + ZENITH * up


def shade(world: World, origin: np.ndarray, directions: np.ndarray, hits: Hits,
          sun: np.ndarray, moving: LabelledMesh | None = None) -> np.ndarray:
    """Linear RGB (N, 3) of camera rays."""
    colour = sky(directions)
    ok = hits.hit
    if not ok.any():
        return colour
    points = origin + directions[ok] * hits.distance[ok, None]
    normal = hits.normal[ok]
    factor, window = texture(points, normal, hits.label[ok])
    albedo = hits.albedo[ok] * factor[:, None]
    albedo[window] = albedo[window] * 0.3 + np.array([0.08, 0.12, 0.16])
    lit = np.clip(normal @ sun, 0.0, None)
    front = lit > 0
    if front.any():  # cast shadows: a second ray towards the sun
        start = points[front] + normal[front] * 0.03
        blocked = world.cast(start, np.broadcast_to(sun, start.shape), moving, shading=False).hit
        lit[np.flatnonzero(front)[blocked]] = 0.0
    ambient = 0.28 + 0.12 * np.clip(normal[:, 2], 0.0, 1.0)
    surface = albedo * (ambient + 0.85 * lit)[:, None]
    haze = 1.0 - np.exp(-hits.distance[ok] / 900.0)
    colour[ok] = surface * (1 - haze[:, None]) + HORIZON * haze[:, None]
    return colour


def to_image(linear: np.ndarray, width: int, height: int, supersample: int,
             rng: np.random.Generator) -> np.ndarray:
    """Average sub-pixel samples, gamma-encode, add a little sensor noise: uint8 (H, W, 3)."""
    s = supersample
    img = linear.reshape(height, s, width, s, 3).mean(axis=(1, 3))
    img = np.clip(img, 0.0, 1.0) ** (1 / 2.2)
    img = img + rng.normal(0.0, 0.01, img.shape)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
