"""Triangle meshes that carry a SemanticKITTI class and a colour per triangle.

Both simulated sensors ray-cast the same meshes, so a lidar point and a camera pixel that see the
same surface get the same class by construction: the ground truth of a scene is the class of the
triangle a ray hits. Primitives here are deliberately simple (boxes, cylinders, jittered spheres,
height-field grids): what matters for calibration is where class boundaries are, not fine detail.
Triangle winding is not kept consistent; the shader turns normals towards the viewer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LabelledMesh:
    """Vertices (V, 3), triangles (T, 3) indices, label (T,) SemanticKITTI ids, albedo (T, 3) 0..1."""

    vertices: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray
    albedo: np.ndarray

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        self.labels = np.asarray(self.labels, dtype=np.uint16).reshape(-1)
        self.albedo = np.asarray(self.albedo, dtype=np.float32).reshape(-1, 3)
        n = len(self.triangles)
        if len(self.labels) != n or len(self.albedo) != n:
            raise ValueError(f"{n} triangles but {len(self.labels)} labels, {len(self.albedo)} colours")
        if n and (self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices)):
            raise ValueError("triangle index out of range")

    def __len__(self) -> int:
        return len(self.triangles)

    @classmethod
    def empty(cls) -> "LabelledMesh":
        return cls(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0), np.zeros((0, 3)))

    @classmethod
    def concat(cls, meshes: list["LabelledMesh"]) -> "LabelledMesh":
        meshes = [m for m in meshes if len(m)]
        if not meshes:
            return cls.empty()
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return cls(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)]),
            np.concatenate([m.labels for m in meshes]),
            np.concatenate([m.albedo for m in meshes]),
        )

    def moved(self, yaw: float, offset: np.ndarray) -> "LabelledMesh":
        """Rotated about z by ``yaw`` (radians) around the origin, then translated."""
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return LabelledMesh(self.vertices @ rot.T + np.asarray(offset, float),
                            self.triangles, self.labels, self.albedo)


class MeshBuilder:
    """Collects labelled parts and concatenates them once (cheaper than growing arrays)."""

    def __init__(self) -> None:
        self._parts: list[LabelledMesh] = []

    def add(self, vertices: np.ndarray, triangles: np.ndarray, label: int,
            albedo: tuple[float, float, float] | np.ndarray) -> None:
        tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        colour = np.broadcast_to(np.asarray(albedo, np.float32), (len(tris), 3))
        self._parts.append(LabelledMesh(vertices, tris, np.full(len(tris), label), colour))

    def add_mesh(self, mesh: LabelledMesh) -> None:
        self._parts.append(mesh)

    def build(self) -> LabelledMesh:
        return LabelledMesh.concat(self._parts)


# ---------------------------------------------------------------------------------------------
# Primitives: each returns (vertices (V, 3), triangles (T, 3)).

_BOX_TRIS = np.array([
    [0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7],  # bottom, top
    [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
    [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
])


def box(center_xy: tuple[float, float], size_xy: tuple[float, float], z0: float, z1: float,
        yaw: float = 0.0, bottom: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """An upright box rotated by ``yaw`` about its centre; the bottom face only if asked."""
    hx, hy = size_xy[0] / 2.0, size_xy[1] / 2.0
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = np.cos(yaw), np.sin(yaw)
    xy = corners @ np.array([[c, s], [-s, c]]) + np.asarray(center_xy, float)
    verts = np.concatenate([np.c_[xy, np.full(4, z0)], np.c_[xy, np.full(4, z1)]])
    tris = _BOX_TRIS if bottom else _BOX_TRIS[2:]
    return verts, tris


def segment_box(p0: np.ndarray, p1: np.ndarray, width: float, z0: float, z1: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """A box of the given width along the 2-D segment p0 -> p1 (walls, fences, rails)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    return box((p0 + p1) / 2.0, (float(np.hypot(*d)), width), z0, z1, float(np.arctan2(d[1], d[0])))


def quad(x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat axis-aligned rectangle."""
    verts = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return verts, np.array([[0, 1, 2], [0, 2, 3]])


def quads(rects: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Many flat rectangles (R, 4) of x0, x1, y0, y1 at one height (lane-marking dashes)."""
    rects = np.asarray(rects, float).reshape(-1, 4)
    x0, x1, y0, y1 = rects.T
    verts = np.stack([np.c_[x0, y0], np.c_[x1, y0], np.c_[x1, y1], np.c_[x0, y1]], 1)
    verts = np.concatenate([verts, np.full((len(rects), 4, 1), z)], 2).reshape(-1, 3)
    base = 4 * np.arange(len(rects))[:, None, None]
    tris = (np.array([[0, 1, 2], [0, 2, 3]])[None] + base).reshape(-1, 3)
    return verts, tris


def cylinder(center_xy: tuple[float, float], radius: float, z0: float, z1: float,
             segments: int = 10, radius_top: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """An upright cylinder (or cone frustum) with a top cap."""
    rt = radius if radius_top is None else radius_top
    a = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.c_[np.cos(a), np.sin(a)]
    cx, cy = center_xy
    bottom = np.c_[ring * radius + (cx, cy), np.full(segments, z0)]
    top = np.c_[ring * rt + (cx, cy), np.full(segments, z1)]
    verts = np.concatenate([bottom, top, [[cx, cy, z1]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    side = np.concatenate([np.c_[i, j, j + segments], np.c_[i, j + segments, i + segments]])
    cap = np.c_[i + segments, j + segments, np.full(segments, 2 * segments)]
    return verts, np.concatenate([side, cap])


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    verts = list(v / np.linalg.norm(v, axis=1, keepdims=True))
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = np.array(new)
    return np.array(verts), f


_UNIT_SPHERE = {n: _icosphere(n) for n in (1, 2)}


def blob(center: tuple[float, float, float], radii: tuple[float, float, float],
         rng: np.random.Generator, roughness: float = 0.18, subdivisions: int = 2
         ) -> tuple[np.ndarray, np.ndarray]:
    """A jittered ellipsoid: an irregular tree crown or bush."""
    unit, tris = _UNIT_SPHERE[subdivisions]
    scale = 1.0 + roughness * rng.uniform(-1.0, 1.0, (len(unit), 1))
    return unit * scale * np.asarray(radii, float) + np.asarray(center, float), tris


def height_grid(x0: float, x1: float, y0: float, y1: float, cell: float,
                height: "callable") -> tuple[np.ndarray, np.ndarray]:
    """A height field z = height(x, y) sampled on a regular grid (terrain, embankments)."""
    nx = max(1, int(np.ceil((x1 - x0) / cell)))
    ny = max(1, int(np.ceil((y1 - y0) / cell)))
    gx, gy = np.meshgrid(np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1), indexing="ij")
    gz = height(gx, gy)
    verts = np.stack([gx, gy, gz], -1).reshape(-1, 3)
    idx = np.arange((nx + 1) * (ny + 1)).reshape(nx + 1, ny + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])


class SmoothNoise:
    """A smooth random 2-D field (sum of a few random sinusoids), cheap to evaluate anywhere."""

    def __init__(self, rng: np.random.Generator, wavelength: float, amplitude: float,
                 waves: int = 6) -> None:
        angles = rng.uniform(0.0, np.pi, waves)
        lengths = wavelength * rng.uniform(0.6, 1.6, waves)
        self._k = np.c_[np.cos(angles), np.sin(angles)] * (2 * np.pi / lengths)[:, None]
        self._phase = rng.uniform(0.0, 2 * np.pi, waves)
        self._amp = amplitude / np.sqrt(waves / 2.0)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        out = np.zeros(np.broadcast(x, y).shape)
        for (kx, ky), ph in zip(self._k, self._phase):
            out += np.sin(kx * x + ky * y + ph)
        return out * self._amp


def _arc_angles(radius: float, a0: float, a1: float, step: float) -> np.ndarray:
    n = max(2, int(np.ceil(abs(a1 - a0) * max(radius, 1e-6) / step)) + 1)
    return np.linspace(a0, a1, n)


def annulus(center_xy: tuple[float, float], r0: float, r1: float, z: float, a0: float = 0.0,
            a1: float = 2 * np.pi, step: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat ring sector between radii r0 < r1 and angles a0 < a1 (r0 = 0 gives a disc
    sector); the outer edge is sampled about every ``step`` metres."""
    a = _arc_angles(r1, a0, a1, step)
    ring = np.c_[np.cos(a), np.sin(a)]
    inner = np.c_[ring * r0 + center_xy, np.full(len(a), z)]
    outer = np.c_[ring * r1 + center_xy, np.full(len(a), z)]
    n = len(a)
    i = np.arange(n - 1)
    tris = np.concatenate([np.c_[i, i + 1, i + n + 1], np.c_[i, i + n + 1, i + n]])
    return np.concatenate([inner, outer]), tris


def ring_wall(center_xy: tuple[float, float], radius: float, z0: float, z1: float,
              a0: float = 0.0, a1: float = 2 * np.pi, step: float = 1.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """A vertical curved wall (a kerb face) on a circle, from angle a0 to a1."""
    a = _arc_angles(radius, a0, a1, step)
    xy = np.c_[np.cos(a), np.sin(a)] * radius + center_xy
    n = len(a)
    verts = np.concatenate([np.c_[xy, np.full(n, z0)], np.c_[xy, np.full(n, z1)]])
    i = np.arange(n - 1)
    return verts, np.concatenate([np.c_[i, i + 1, i + n + 1], np.c_[i, i + n + 1, i + n]])


def polar_height(center_xy: tuple[float, float], radius: float, height: "callable",
                 rings: int = 12, step: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A round height field z = height(r) (r from the centre) whose rim lies exactly on the
    circle, so a raised island meets its kerb without a gap."""
    r = np.linspace(0.0, radius, rings + 1)[1:]
    a = np.linspace(0.0, 2 * np.pi, max(8, int(2 * np.pi * radius / step)), endpoint=False)
    na = len(a)
    rr, aa = np.meshgrid(r, a, indexing="ij")
    xy = np.stack([rr * np.cos(aa), rr * np.sin(aa)], -1).reshape(-1, 2) + center_xy
    verts = np.concatenate([[[center_xy[0], center_xy[1], float(height(np.zeros(1))[0])]],
                            np.c_[xy, height(rr.ravel())]])
    j = np.arange(na)
    k = (j + 1) % na
    tris = [np.c_[np.zeros(na, int), 1 + j, 1 + k]]  # the centre fan
    for ring in range(rings - 1):
        a_, b_ = 1 + ring * na, 1 + (ring + 1) * na
        tris += [np.c_[a_ + j, a_ + k, b_ + k], np.c_[a_ + j, b_ + k, b_ + j]]
    return verts, np.concatenate(tris)


def oriented_box(center: np.ndarray, size: tuple[float, float, float], rotation: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A closed box of ``size`` (x, y, z) in a frame rotated by the 3x3 ``rotation`` about its
    centre (a camera housing aligned with the camera, not with the ground)."""
    h = np.asarray(size, float) / 2.0
    corners = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                        [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float) * h
    return corners @ np.asarray(rotation, float).T + np.asarray(center, float), _BOX_TRIS
