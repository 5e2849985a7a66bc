"""Per-voxel shape features of a lidar scan: what the point labeller's classifier sees.

A class is told by shape at several scales, measured in metres so that any lidar gives the
same numbers for the same object (beam count, pattern and mount height only change how many
points fall on it):

* the **local neighbourhood** (the voxel's nearest voxels at two scales): linearity, planarity,
  scattering, verticality of the normal and of the main axis, size and height span;
* the **column** above the voxel's ground cell: how high the tallest object there reaches and
  where it starts (a car's roof is 1.5 m up, a facade's 10 m, a canopy hangs above a trunk);
* the **object** (connected occupied ground cells of non-ground voxels): footprint length and
  width, top height, size;
* the **ground around**: the step to the lowest ground nearby (a kerb puts the sidewalk
  0.1-0.15 m above the road), roughness, the kerb rules' road / sidewalk / terrain guess, and
  how far the nearest tall object stands (sidewalks run along facades);
* the voxel's **height above the ground** and its horizontal distance from the sensor.

Not its height above the sensor's own ground level: a road that climbs 0.1-0.2 m over 30 m
(PJLab's frames) then looked like KITTI's raised sidewalk and came out terrain.

Ground (Patchwork++) and non-ground points are voxelised apart, so a voxel at the foot of a
wall does not mix the two. Intensity is not used: its scale differs between lidars, and the
synthetic scenes' intensity is a per-class table, which a classifier would learn instead of shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import small_gicp
from scipy import ndimage

from semcal_ros.segmentation import forest as _forest  # noqa: F401  (numba's threading set-up)

#: Feature columns, in the order of :attr:`VoxelFeatures.values` (the model file stores them
#: and is refused when they differ).
FEATURE_NAMES: tuple[str, ...] = (
    "is_ground", "height", "range",
    "s_linearity", "s_planarity", "s_scattering", "s_normal_z", "s_axis_z", "s_size", "s_zspan",
    "l_linearity", "l_planarity", "l_scattering", "l_normal_z", "l_axis_z", "l_size", "l_zspan",
    "col_top", "col_bottom", "col_top_wide", "col_count",
    "obj_length", "obj_width", "obj_top", "obj_cells",
    "ground_step", "ground_step_wide", "ground_rough", "ground_rule", "dist_tall",
)


@dataclass(frozen=True)
class FeatureParams:
    """Scales of the features (metres unless said); the model is trained with these."""

    voxel: float = 0.2  # points are grouped in voxels of this size; one feature row per voxel
    knn_small: int = 10  # nearest voxels of the small-scale neighbourhood
    knn_large: int = 32  # ... and of the large-scale one
    column_cell: float = 0.5  # ground cell of the column features
    column_cell_wide: float = 1.5  # ... and of the wide column's top
    object_cell: float = 0.3  # occupancy grid whose connected cells form objects
    object_min_height: float = 0.25  # voxels lower than this do not join objects
    ground_cell: float = 0.3  # grid of the ground-step features
    step_window: float = 2.7  # lowest ground within this square window (kerb step)
    step_window_wide: float = 6.3  # ... and within this wider one
    tall_height: float = 1.5  # objects reaching this high count for ``dist_tall``


@dataclass
class VoxelFeatures:
    """The scan's voxels: which voxel each point is in, the feature rows, the neighbours."""

    inverse: np.ndarray  # (N,) voxel of each point
    values: np.ndarray  # (V, F) float32 features, columns as FEATURE_NAMES
    neighbours: np.ndarray  # (V, knn_small) voxel indices of each voxel's nearest voxels
    ground: np.ndarray  # (V,) bool: a ground voxel


def _voxelize(xyz: np.ndarray, ground: np.ndarray, size: float):
    """(voxel of each point, first point of each voxel, points per voxel, centroids); ground
    and non-ground points never share a voxel."""
    key = np.floor(xyz / size).astype(np.int64)
    key -= key.min(axis=0)
    dims = key.max(axis=0) + 1
    flat = ((key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]) * 2 + ground
    _, first, inverse, count = np.unique(flat, return_index=True, return_inverse=True,
                                         return_counts=True)
    centroid = np.stack([np.bincount(inverse, xyz[:, i]) / count for i in range(3)], axis=1)
    return inverse, first, count, centroid


@nb.njit(cache=True, nogil=True)
def _eigvec(a00, a01, a02, a11, a12, a22, lam):  # pragma: no cover - numba
    """Unit eigenvector of the symmetric 3x3 matrix for eigenvalue ``lam``: the longest cross
    product of two rows of (A - lam I); (0, 0, 1) for a degenerate matrix."""
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best = (0.0, 0.0, 1.0)
    best_n = 1e-30
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        c = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
        n = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        if n > best_n:
            best, best_n = c, n
    if best_n <= 1e-30:
        return 0.0, 0.0, 1.0
    s = 1.0 / np.sqrt(best_n)
    return best[0] * s, best[1] * s, best[2] * s


@nb.njit(parallel=True, cache=True, nogil=True)
def _eigen_features(centroid, idx, ks):  # pragma: no cover - numba
    """For each voxel and each neighbourhood size k in ``ks`` (its first k neighbours in
    ``idx``): linearity, planarity, scattering, |normal z|, |main axis z|, size (sqrt of the
    largest eigenvalue) and height span. Eigenvalues in closed form (Smith 1961)."""
    n = idx.shape[0]
    out = np.zeros((n, 7 * len(ks)), np.float32)
    for i in nb.prange(n):
        for s in range(len(ks)):
            k = ks[s]
            mx = my = mz = 0.0
            zmin, zmax = 1e30, -1e30
            for j in range(k):
                p = idx[i, j]
                mx += centroid[p, 0]
                my += centroid[p, 1]
                mz += centroid[p, 2]
                zmin = min(zmin, centroid[p, 2])
                zmax = max(zmax, centroid[p, 2])
            mx /= k
            my /= k
            mz /= k
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            for j in range(k):
                p = idx[i, j]
                dx = centroid[p, 0] - mx
                dy = centroid[p, 1] - my
                dz = centroid[p, 2] - mz
                a00 += dx * dx
                a01 += dx * dy
                a02 += dx * dz
                a11 += dy * dy
                a12 += dy * dz
                a22 += dz * dz
            a00 /= k
            a01 /= k
            a02 /= k
            a11 /= k
            a12 /= k
            a22 /= k
            p1 = a01 * a01 + a02 * a02 + a12 * a12
            q = (a00 + a11 + a22) / 3.0
            p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
            if p2 <= 1e-24:
                l1 = l2 = l3 = q
            else:
                pp = np.sqrt(p2 / 6.0)
                b00, b11, b22 = (a00 - q) / pp, (a11 - q) / pp, (a22 - q) / pp
                b01, b02, b12 = a01 / pp, a02 / pp, a12 / pp
                r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                     + b02 * (b01 * b12 - b11 * b02)) / 2.0
                r = min(1.0, max(-1.0, r))
                phi = np.arccos(r) / 3.0
                l1 = q + 2.0 * pp * np.cos(phi)
                l3 = q + 2.0 * pp * np.cos(phi + 2.0 * np.pi / 3.0)
                l2 = 3.0 * q - l1 - l3
            e1 = max(l1, 1e-10)
            e2 = min(max(l2, 1e-10), e1)
            e3 = min(max(l3, 1e-10), e2)
            normal = _eigvec(a00, a01, a02, a11, a12, a22, l3)
            axis = _eigvec(a00, a01, a02, a11, a12, a22, l1)
            o = 7 * s
            out[i, o] = (e1 - e2) / e1
            out[i, o + 1] = (e2 - e3) / e1
            out[i, o + 2] = e3 / e1
            out[i, o + 3] = abs(normal[2])
            out[i, o + 4] = abs(axis[2])
            out[i, o + 5] = np.sqrt(e1)
            out[i, o + 6] = zmax - zmin
    return out


def nearest_voxels(centroid: np.ndarray, k: int) -> np.ndarray:
    """(V, k) int64: each voxel's k nearest voxels (itself first), nearest first.

    small_gicp's k-d tree: the same neighbours as scipy's cKDTree in half its time on a KITTI
    scan (118 vs 216 ms CPU for 32 neighbours of 32k voxels, one thread; the 2-thread query
    costs more CPU on 2 loaded cores and is not used)."""
    pts = np.ascontiguousarray(centroid, np.float64)
    if len(pts) < 2:
        return np.zeros((len(pts), k), np.int64)
    idx, _ = small_gicp.KdTree(pts, 1).batch_knn_search(pts, k, 1)
    return np.ascontiguousarray(idx, np.int64).reshape(len(pts), k)


def _neighbourhoods(centroid: np.ndarray, params: FeatureParams
                    ) -> tuple[np.ndarray, np.ndarray]:
    """((V, 14) eigen features at the small and the large scale, (V, k_small) neighbours)."""
    n = len(centroid)
    k_large = min(params.knn_large, n)
    k_small = min(params.knn_small, n)
    idx = nearest_voxels(centroid, k_large)
    feats = _eigen_features(np.ascontiguousarray(centroid, np.float64), idx,
                            np.array([k_small, k_large], np.int64))
    return feats, idx[:, :k_small]


class _Grid:
    """A square 2-D grid covering the given points; ``flat(xy)`` gives each point's cell."""

    def __init__(self, xy: np.ndarray, cell: float) -> None:
        self.cell = cell
        self.lo = xy.min(axis=0) - cell
        self.shape = tuple(int(s) for s in np.floor((xy.max(axis=0) - self.lo) / cell) + 2)

    def ij(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ij = np.floor((xy - self.lo) / self.cell).astype(np.int64)
        return (np.clip(ij[:, 0], 0, self.shape[0] - 1), np.clip(ij[:, 1], 0, self.shape[1] - 1))

    def flat(self, xy: np.ndarray) -> np.ndarray:
        i, j = self.ij(xy)
        return i * self.shape[1] + j

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]


def _column_features(xy: np.ndarray, height: np.ndarray, objects: np.ndarray,
                     params: FeatureParams) -> np.ndarray:
    """(V, 4): top and bottom height of the non-ground voxels in each voxel's column, the top in
    a wider column, and how many non-ground voxels the column holds."""
    out = np.zeros((len(xy), 4), np.float32)
    if not objects.any():
        return out
    grid = _Grid(xy, params.column_cell)
    cell = grid.flat(xy)
    top = np.full(grid.size, -1.0)
    bottom = np.full(grid.size, 30.0)
    np.maximum.at(top, cell[objects], height[objects])
    np.minimum.at(bottom, cell[objects], height[objects])
    count = np.bincount(cell[objects], minlength=grid.size)
    wide = _Grid(xy, params.column_cell_wide)
    wcell = wide.flat(xy)
    wtop = np.full(wide.size, -1.0)
    np.maximum.at(wtop, wcell[objects], height[objects])
    out[:, 0] = top[cell]
    out[:, 1] = np.where(count[cell] > 0, bottom[cell], -1.0)
    out[:, 2] = wtop[wcell]
    out[:, 3] = count[cell]
    return out


def _object_features(xy: np.ndarray, height: np.ndarray, objects: np.ndarray,
                     params: FeatureParams) -> tuple[np.ndarray, np.ndarray, _Grid]:
    """(V, 4) object features (footprint length, width, top height, occupied cells; zeros for
    voxels in no object) and the occupancy grid (True where an object stands) with its grid."""
    out = np.zeros((len(xy), 4), np.float32)
    grid = _Grid(xy, params.object_cell)
    cell = grid.flat(xy)
    member = objects & (height >= params.object_min_height)
    occupied = np.zeros(grid.size, bool)
    occupied[cell[member]] = True
    occupied = occupied.reshape(grid.shape)
    if not member.any():
        return out, occupied, grid
    comp, ncomp = ndimage.label(occupied, structure=np.ones((3, 3)))
    comp = comp.ravel()
    ii, jj = np.nonzero(occupied)
    c = comp[ii * grid.shape[1] + jj]
    x, y = ii * grid.cell, jj * grid.cell
    n = np.bincount(c, minlength=ncomp + 1).astype(np.float64)
    safe = np.maximum(n, 1)
    mx, my = np.bincount(c, x, ncomp + 1) / safe, np.bincount(c, y, ncomp + 1) / safe
    sxx = np.bincount(c, x * x, ncomp + 1) / safe - mx * mx
    syy = np.bincount(c, y * y, ncomp + 1) / safe - my * my
    sxy = np.bincount(c, x * y, ncomp + 1) / safe - mx * my
    half = (sxx + syy) / 2
    root = np.sqrt(np.maximum(((sxx - syy) / 2) ** 2 + sxy ** 2, 0))
    # 3.5 sigma of the cells' spread along the principal axes, plus one cell
    length = 3.5 * np.sqrt(np.maximum(half + root, 0)) + grid.cell
    width = 3.5 * np.sqrt(np.maximum(half - root, 0)) + grid.cell
    top = np.zeros(ncomp + 1)
    vc = comp[cell]
    in_object = objects & (vc > 0)
    np.maximum.at(top, vc[in_object], height[in_object])
    vc = np.where(objects, vc, 0)
    out[:, 0], out[:, 1], out[:, 2], out[:, 3] = length[vc], width[vc], top[vc], n[vc]
    out[vc == 0] = 0.0
    return out, occupied, grid


def _ground_features(xy: np.ndarray, z: np.ndarray, ground: np.ndarray, rule: np.ndarray,
                     tall: np.ndarray, params: FeatureParams) -> np.ndarray:
    """(V, 5): ground height above the lowest ground in a window and in a wider one, the height
    spread of the voxel's ground cell, the kerb rules' class (0 road, 1 sidewalk, 2 terrain,
    -1 for a non-ground voxel) and the distance to the nearest tall object (metres, capped)."""
    out = np.zeros((len(xy), 5), np.float32)
    grid = _Grid(xy, params.ground_cell)
    cell = grid.flat(xy)
    out[:, 3] = rule
    if ground.any():
        gc = cell[ground]
        count = np.bincount(gc, minlength=grid.size).astype(np.float64)
        mean = np.bincount(gc, z[ground], grid.size) / np.maximum(count, 1)
        sq = np.bincount(gc, z[ground] ** 2, grid.size) / np.maximum(count, 1)
        rough = np.sqrt(np.maximum(sq - mean ** 2, 0))
        low = np.where(count > 0, mean, np.inf).reshape(grid.shape)
        steps = []
        for window in (params.step_window, params.step_window_wide):
            size = max(3, int(round(window / params.ground_cell)) | 1)
            lowest = ndimage.minimum_filter(low, size=size, mode="constant", cval=np.inf).ravel()
            steps.append(np.where(np.isfinite(lowest[cell]), z - lowest[cell], 0.0))
        out[:, 0], out[:, 1] = steps
        out[:, 2] = np.where(ground, rough[cell], 0.0)
    tall_grid = np.zeros(grid.size, bool)
    tall_grid[cell[tall]] = True
    if tall_grid.any():
        dist = ndimage.distance_transform_edt(~tall_grid.reshape(grid.shape)).ravel()
        out[:, 4] = np.minimum(dist[cell] * params.ground_cell, 30.0)
    else:
        out[:, 4] = 30.0
    return out


def voxel_features(xyz: np.ndarray, ground: np.ndarray, height: np.ndarray, rule: np.ndarray,
                   params: FeatureParams = FeatureParams()) -> VoxelFeatures:
    """Features of a scan's voxels.

    ``xyz`` (N, 3) in the lidar frame (z up, sensor at the origin), ``ground`` (N,) the ground
    segmentation, ``height`` (N,) each point's height above the ground surface, ``rule`` (N,)
    the kerb rules' class of ground points (0 road, 1 sidewalk, 2 terrain; any value for other
    points).
    """
    inverse, first, count, centroid = _voxelize(xyz, ground, params.voxel)
    vground = ground[first]
    vheight = (np.bincount(inverse, height) / count).astype(np.float32)
    n = len(centroid)
    values = np.zeros((n, len(FEATURE_NAMES)), np.float32)
    values[:, 0] = vground
    values[:, 1] = vheight
    values[:, 2] = np.hypot(centroid[:, 0], centroid[:, 1])
    k_small = min(params.knn_small, n)
    neighbours = np.zeros((n, k_small), np.int64)
    for part in (vground, ~vground):
        members = np.flatnonzero(part)
        if len(members) < 3:
            continue
        eigen, idx = _neighbourhoods(centroid[members], params)
        values[members, 3:17] = eigen
        pad = np.repeat(idx[:, -1:], k_small - idx.shape[1], axis=1)
        neighbours[members] = members[np.concatenate([idx, pad], axis=1)]
    objects = ~vground
    xy = centroid[:, :2]
    values[:, 17:21] = _column_features(xy, vheight, objects, params)
    obj, _, _ = _object_features(xy, vheight, objects, params)
    values[:, 21:25] = obj
    vrule = np.where(vground, rule[first], -1).astype(np.float32)
    tall = objects & (values[:, 23] >= params.tall_height)
    values[:, 25:30] = _ground_features(xy, centroid[:, 2], vground, vrule, tall, params)
    return VoxelFeatures(inverse, values, neighbours, vground)
