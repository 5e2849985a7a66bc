"""Compiled per-point loops of the map builder (numba): one pass each, no temporaries.

The builder touches every point of every scan a few times: range filter, de-skew, the move into
the map frame, and the majority-label voxel grid (per scan and at every merge). In numpy each of
those is a chain of whole-array temporaries (the de-skew alone builds a rotation per point) and
the voxel grid is a sort; here each is one loop over the points, and the voxel grid a hash table
(O(N), no sort). ``filters.voxel_downsample`` and ``deskew`` keep their numpy forms as the
readable definitions; the tests check these kernels against them.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_EMPTY = np.int64(-1)


@nb.njit(cache=True, nogil=True)
def prepare_points(xyz: np.ndarray, times: np.ndarray, twist: np.ndarray, pose: np.ndarray,
                   d_min: float, d_max: float, azimuth: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Range filter, de-skew and the move into the map frame in one pass.

    ``xyz`` (N, 3) in the lidar frame; per-point seconds from the pose instant in ``times`` (N,)
    or, with ``times`` empty and ``azimuth`` = (reference azimuth rad, sign, period s), from the
    azimuth (deskew.azimuth_times); ``twist`` (6,) body velocity (rho, phi) per second (empty:
    no de-skew); ``pose`` 4x4 lidar -> map. A point is kept when finite and d_min <= |x| <= d_max
    (as the sensor saw it). Returns (kept points in the map frame (M, 3) float64, kept mask (N,)).
    De-skew: ``exp(t xi) @ x`` with the closed-form SE(3) exponential (deskew.se3_exp_points).
    """
    n = xyz.shape[0]
    keep = np.zeros(n, np.bool_)
    out = np.empty((n, 3))
    deskew = twist.shape[0] == 6 and (times.shape[0] == n or azimuth.shape[0] == 3)
    from_azimuth = times.shape[0] != n
    rx = ry = rz = px = py = pz = 0.0
    if deskew:
        rx, ry, rz, px, py, pz = twist[0], twist[1], twist[2], twist[3], twist[4], twist[5]
    ref = sign = period = 0.0
    if from_azimuth and deskew:
        ref, sign, period = azimuth[0], azimuth[1], azimuth[2]
    # phi x rho and phi x (phi x rho)
    c1x, c1y, c1z = py * rz - pz * ry, pz * rx - px * rz, px * ry - py * rx
    c2x, c2y, c2z = py * c1z - pz * c1y, pz * c1x - px * c1z, px * c1y - py * c1x
    nphi = np.sqrt(px * px + py * py + pz * pz)
    lo2, hi2 = d_min * d_min, d_max * d_max
    m = 0
    for i in range(n):
        x, y, z = float(xyz[i, 0]), float(xyz[i, 1]), float(xyz[i, 2])
        d2 = x * x + y * y + z * z
        if not (d2 <= hi2 and d2 >= lo2):  # also drops NaN
            continue
        keep[i] = True
        if deskew:
            if from_azimuth:
                a = np.arctan2(y, x) - ref
                while a > np.pi:  # wrapped to (-pi, pi]
                    a -= 2.0 * np.pi
                while a <= -np.pi:
                    a += 2.0 * np.pi
                t = sign * a / (2.0 * np.pi) * period
            else:
                t = times[i]
            th = abs(t) * nphi
            th2 = th * th
            if th < 0.1:  # series (a sweep turns a few hundredths of a radian): next terms
                # th^6 / 40320 and less, below 1e-12
                a = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
                b = 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0
                sa = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
                sb = a
            else:
                a, b = (1.0 - np.cos(th)) / th2, (th - np.sin(th)) / (th2 * th)
                sa, sb = np.sin(th) / th, a
            tx = t * rx + a * t * t * c1x + b * t * t * t * c2x
            ty = t * ry + a * t * t * c1y + b * t * t * t * c2y
            tz = t * rz + a * t * t * c1z + b * t * t * t * c2z
            # rotation exp(t phi) applied by Rodrigues: x cos + (w x x) sin/th + w (w.x) (1-cos)/th^2
            wx, wy, wz = t * px, t * py, t * pz
            wdx = wx * x + wy * y + wz * z
            x, y, z = (x + sa * (wy * z - wz * y) + sb * (wx * wdx - th2 * x) + tx,
                       y + sa * (wz * x - wx * z) + sb * (wy * wdx - th2 * y) + ty,
                       z + sa * (wx * y - wy * x) + sb * (wz * wdx - th2 * z) + tz)
        out[m, 0] = pose[0, 0] * x + pose[0, 1] * y + pose[0, 2] * z + pose[0, 3]
        out[m, 1] = pose[1, 0] * x + pose[1, 1] * y + pose[1, 2] * z + pose[1, 3]
        out[m, 2] = pose[2, 0] * x + pose[2, 1] * y + pose[2, 2] * z + pose[2, 3]
        m += 1
    return out[:m].copy(), keep


@nb.njit(cache=True, nogil=True)
def span(xyz: np.ndarray) -> float:
    """The largest extent of the points along x, y or z (one pass; NaN if any is NaN)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(xyz.shape[0]):
        for k in range(3):
            v = xyz[i, k]
            if not v >= lo[k]:  # NaN propagates
                lo[k] = v
            if not v <= hi[k]:
                hi[k] = v
    return max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])


@nb.njit(cache=True, nogil=True)
def _hash(key: np.int64, mask: np.int64) -> np.int64:
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64(h >> np.uint64(20)) & mask


@nb.njit(cache=True, nogil=True)
def _keys_by_tile(xyz: np.ndarray, voxel, tile_cells: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's voxel key (cells packed 21 bits per axis), the point indices grouped by
    horizontal tiles of ``tile_cells`` voxels (a stable counting sort) and the tiles' start
    offsets; one tile when the tile grid would be larger than the cloud. The cells are computed
    here once: the hash pass reads the keys instead of dividing every coordinate again."""
    n = xyz.shape[0]
    keys = np.empty(n, np.int64)
    tile = np.empty(n, np.int64)
    ty = np.empty(n, np.int64)
    for i in range(n):
        cx = np.int64(np.floor(xyz[i, 0] / voxel))
        cy = np.int64(np.floor(xyz[i, 1] / voxel))
        cz = np.int64(np.floor(xyz[i, 2] / voxel))
        keys[i] = ((cx & 0x1FFFFF) << 42) | ((cy & 0x1FFFFF) << 21) | (cz & 0x1FFFFF)
        tile[i] = cx // tile_cells
        ty[i] = cy // tile_cells
    x0, x1, y0, y1 = tile.min(), tile.max(), ty.min(), ty.max()
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    if nx * ny > 2 * n + 1024:  # sparse and far apart: one tile
        starts = np.zeros(2, np.int64)
        starts[1] = n
        return keys, np.arange(n), starts
    counts = np.zeros(nx * ny + 1, np.int64)
    for i in range(n):
        tile[i] = (tile[i] - x0) * ny + (ty[i] - y0)
        counts[tile[i] + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    perm = np.empty(n, np.int64)
    for i in range(n):
        perm[fill[tile[i]]] = i
        fill[tile[i]] += 1
    return keys, perm, starts


@nb.njit(cache=True, nogil=True)
def voxel_majority(xyz: np.ndarray, voxel, label: np.ndarray, table: np.ndarray,
                   n_classes: int, labelled: np.ndarray, extra: np.ndarray,
                   tile_cells: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One point per occupied voxel: the centroid of its winning class's points.

    ``voxel`` has the points' precision (float32 points are binned as float32 numbers);
    ``label`` (N,) the points' class ids (empty: one class), ``table`` class id -> class index
    0..n_classes-1 (classes in ascending id order), ``labelled`` (n_classes,) bool: False for
    ``unlabeled``, which only wins a voxel nobody else is in; then the most points win, ties to
    the smaller id (filters.voxel_downsample's rule). ``extra`` (N, E) float columns (a scan's
    float32 intensity as it is: no float64 copy) averaged in float64 over the same points.
    Returns (points (V, 3) float64, class index (V,), extras (V, E) float64), voxels tile by
    tile.

    Points are taken tile by tile (``tile_cells`` voxels square, a counting sort), each tile
    through an open-addressing hash table of its own size, so the table stays in the cache: a
    merged cloud of a million points costs a third of what one table for all of it did. Each
    voxel keeps a short chain of (class, count, sums) entries; nothing is sorted.
    """
    n = xyz.shape[0]
    n_extra = extra.shape[1]
    width = 4 + n_extra
    has_label = label.shape[0] == n
    keys, perm, starts = _keys_by_tile(xyz, voxel, tile_cells)
    biggest = 0
    for t in range(starts.shape[0] - 1):
        biggest = max(biggest, starts[t + 1] - starts[t])
    size = 1
    while size < 2 * biggest + 2:
        size *= 2
    slot_key = np.empty(size, np.int64)  # the tile's hash table: voxel key ...
    slot_head = np.empty(size, np.int64)  # ... and the voxel's newest entry
    order = np.empty(n, np.int64)  # slot of each voxel of the tile, in order of appearance
    entry_class = np.empty(n, np.int64)  # per entry: its class and the next entry of the voxel
    entry_next = np.empty(n, np.int64)
    sums = np.empty((n, width))  # per entry [count, x, y, z, extras...]
    points = np.empty((n, 3))
    best = np.empty(n, np.int64)
    extras = np.empty((n, n_extra))
    n_vox = 0
    for t in range(starts.shape[0] - 1):
        lo, hi = starts[t], starts[t + 1]
        if hi == lo:
            continue
        tsize = 1
        while tsize < 2 * (hi - lo) + 2:
            tsize *= 2
        mask = np.int64(tsize - 1)
        slot_key[:tsize] = _EMPTY
        first = n_vox
        n_entry = 0
        for j in range(lo, hi):
            i = perm[j]
            key = keys[i]
            h = _hash(key, mask)
            while slot_key[h] != _EMPTY and slot_key[h] != key:
                h = (h + 1) & mask
            c = table[label[i]] if has_label else 0
            if slot_key[h] == _EMPTY:
                slot_key[h] = key
                slot_head[h] = _EMPTY
                order[n_vox] = h
                n_vox += 1
            e = slot_head[h]
            while e >= 0 and entry_class[e] != c:
                e = entry_next[e]
            if e < 0:
                e = lo + n_entry  # entries of this tile live in [lo, hi)
                n_entry += 1
                entry_class[e] = c
                entry_next[e] = slot_head[h]
                slot_head[h] = e
                for k in range(width):
                    sums[e, k] = 0.0
            sums[e, 0] += 1.0
            sums[e, 1] += xyz[i, 0]
            sums[e, 2] += xyz[i, 1]
            sums[e, 3] += xyz[i, 2]
            for k in range(n_extra):
                sums[e, 4 + k] += extra[i, k]
        for v in range(first, n_vox):  # the tile's voxels, before its table is reused
            top, top_score, top_class = -1, -1.0, n_classes
            e = slot_head[order[v]]
            while e >= 0:
                c = entry_class[e]
                score = sums[e, 0] + (n + 1.0) * labelled[c]
                if score > top_score or (score == top_score and c < top_class):
                    top, top_score, top_class = e, score, c
                e = entry_next[e]
            k = sums[top, 0]
            best[v] = top_class
            points[v, 0] = sums[top, 1] / k
            points[v, 1] = sums[top, 2] / k
            points[v, 2] = sums[top, 3] / k
            for j in range(n_extra):
                extras[v, j] = sums[top, 4 + j] / k
    return points[:n_vox].copy(), best[:n_vox].copy(), extras[:n_vox].copy()
