"""numba splat renderer: same arithmetic as ``reference`` (so the same image), much faster.

Why numba and not a library: no available renderer does strict z-buffered label splats on the CPU
at this speed (Open3D's offscreen renderer needs software Vulkan and is ~100x slower; see
shared/notes/performance-facts.md). Speed comes from four things: chunks of 1024 Morton-sorted
points are skipped when their bounding sphere is outside the view frustum; each thread owns a
z-buffer (no atomics) merged at the end; a chunk's points are projected in one branch-free pass over
contiguous x, y, z rows (vectorised) before its discs are written, with a min-store per pixel and no
branch; points are read as float32 and computed in float64 exactly as the reference does.
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np

from semcal_ros.engine.camera import MODEL_ID, distort, distort_rational, project_equidistant
from semcal_ros.engine.labels import INVALID
from semcal_ros.engine.render.lod import chunk_stride, drawn_count
from semcal_ros.engine.render.prepare import CHUNK, PreparedMap
from semcal_ros.engine.render.view import EMPTY_KEY, MAX_DEPTH_MM, RADIUS_STEPS, View

# OpenMP is in the numba wheel; without this numba first probes TBB and warns about an old one.
# Idle pool threads sleep instead of spinning: on 2 shared cores a spinning thread steals the
# time of the other jobs (measured: 10-20 % less CPU per render, same wall time).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
if not os.environ.get("NUMBA_THREADING_LAYER"):
    numba.config.THREADING_LAYER = "omp"  # type: ignore[attr-defined]

_distort = numba.njit(cache=True, inline="always")(distort)
_distort_rational = numba.njit(cache=True, inline="always")(distort_rational)
RATIONAL = MODEL_ID["rational_polynomial"]
EQUIDISTANT = MODEL_ID["equidistant"]


@numba.njit(cache=True, inline="always")
def _chunk_visible(c, rad, r, t, near, far, bounds):
    xc = r[0, 0] * c[0] + r[0, 1] * c[1] + r[0, 2] * c[2] + t[0]
    yc = r[1, 0] * c[0] + r[1, 1] * c[1] + r[1, 2] * c[2] + t[1]
    zc = r[2, 0] * c[0] + r[2, 1] * c[1] + r[2, 2] * c[2] + t[2]
    if zc + rad <= near:
        return False
    if math.sqrt(xc * xc + yc * yc + zc * zc) - rad >= far:
        return False
    # frustum side planes x - b z = 0 etc.; outside if the sphere is wholly beyond one of them
    xmin, xmax, ymin, ymax = bounds[0], bounds[1], bounds[2], bounds[3]
    if (xc - xmax * zc) / math.sqrt(1.0 + xmax * xmax) > rad:
        return False
    if (xmin * zc - xc) / math.sqrt(1.0 + xmin * xmin) > rad:
        return False
    if (yc - ymax * zc) / math.sqrt(1.0 + ymax * ymax) > rad:
        return False
    if (ymin * zc - yc) / math.sqrt(1.0 + ymin * ymin) > rad:
        return False
    return True


@numba.njit(cache=True, inline="always")
def _chunk_visible_fisheye(c, rad, r, t, near, far, limit):
    """The equidistant lens' cull: a cone of half-angle ``limit`` (it may exceed 90 deg) about
    the optical axis, and the near/far ranges. The sphere is out when its nearest possible ray
    (the centre's angle minus the sphere's angular radius) is beyond the cone."""
    xc = r[0, 0] * c[0] + r[0, 1] * c[1] + r[0, 2] * c[2] + t[0]
    yc = r[1, 0] * c[0] + r[1, 1] * c[1] + r[1, 2] * c[2] + t[1]
    zc = r[2, 0] * c[0] + r[2, 1] * c[1] + r[2, 2] * c[2] + t[2]
    cdist = math.sqrt(xc * xc + yc * yc + zc * zc)
    if cdist + rad <= near or cdist - rad >= far:
        return False
    if cdist <= rad:
        return True
    angle = math.atan2(math.sqrt(xc * xc + yc * yc), zc)
    return angle - math.asin(rad / cdist) <= limit


@numba.njit(cache=True, inline="always", error_model="numpy")
def _project_pinhole(coords, first, m, r, t, intr, dist_c, distorted, rational, bounds, lam, limit,
                     near, far, ok, uf, vf, sf, ds):
    """Pass 1 for the pinhole models (plumb_bob, rational_polynomial): pixel, radius step and
    range of points ``first .. first + m``, and whether each is in view, into the thread's
    scratch rows. Branch-free over contiguous x, y, z rows, so LLVM runs it four points per
    instruction (measured: 2.5x faster than the same arithmetic point by point from (N, 3))."""
    xs, ys, zs = coords[0], coords[1], coords[2]
    r00, r01, r02, r10, r11, r12 = r[0, 0], r[0, 1], r[0, 2], r[1, 0], r[1, 1], r[1, 2]
    r20, r21, r22, t0, t1, t2 = r[2, 0], r[2, 1], r[2, 2], t[0], t[1], t[2]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist_c[0], dist_c[1], dist_c[2], dist_c[3], dist_c[4]
    k4, k5, k6 = dist_c[5], dist_c[6], dist_c[7]
    xmin, xmax, ymin, ymax = bounds[0], bounds[1], bounds[2], bounds[3]
    for j in range(m):
        x = np.float64(xs[first + j])
        y = np.float64(ys[first + j])
        z = np.float64(zs[first + j])
        xc = r00 * x + r01 * y + r02 * z + t0
        yc = r10 * x + r11 * y + r12 * z + t1
        zc = r20 * x + r21 * y + r22 * z + t2
        dist = math.sqrt(xc * xc + yc * yc + zc * zc)
        xn = xc / zc
        yn = yc / zc
        good = (zc > near) & (dist < far) & (xn >= xmin) & (xn <= xmax) & (yn >= ymin) & \
            (yn <= ymax)
        if rational:
            good = good & (xn * xn + yn * yn <= limit)
            xd, yd = _distort_rational(xn, yn, k1, k2, p1, p2, k3, k4, k5, k6)
        elif distorted:
            xd, yd = _distort(xn, yn, k1, k2, p1, p2, k3)
        else:
            xd, yd = xn, yn
        ok[j] = good
        uf[j] = math.floor(fx * xd + cx + 0.5)
        vf[j] = math.floor(fy * yd + cy + 0.5)
        sf[j] = math.floor(lam / dist * RADIUS_STEPS)
        ds[j] = dist


@numba.njit(cache=True, inline="always", error_model="numpy")
def _project_fisheye(coords, first, m, r, t, intr, dist_c, lam, limit, near, far, span, width,
                     height, ok, uf, vf, sf, ds):
    """Pass 1 for the equidistant lens (point by point: atan2 does not vectorise). Centres off
    the image whose discs cannot reach it are out, as in reference.project_points."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for j in range(m):
        x = np.float64(coords[0, first + j])
        y = np.float64(coords[1, first + j])
        z = np.float64(coords[2, first + j])
        xc = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
        yc = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
        zc = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
        dist = math.sqrt(xc * xc + yc * yc + zc * zc)
        ok[j] = False
        if not (dist > near and dist < far):
            continue
        # k1..k4 of the equidistant model are the first four coefficients
        xd, yd, theta = project_equidistant(xc, yc, zc, dist_c[0], dist_c[1], dist_c[2],
                                            dist_c[3])
        if not theta <= limit:
            continue
        u = math.floor(fx * xd + cx + 0.5)
        v = math.floor(fy * yd + cy + 0.5)
        if not (-span <= u < width + span and -span <= v < height + span):
            continue
        ok[j] = True
        uf[j] = u
        vf[j] = v
        ds[j] = dist
        sf[j] = math.floor(lam / dist * RADIUS_STEPS)


@numba.njit(cache=True, inline="always")
def _splat(zb, u, v, dist, lab, s0, s1, span, offsets, linear, falloff, rim, width, height):
    """One point's disc into the z-buffer: offsets ``s0:s1`` of the disc table around (u, v).
    Every write stores the minimum instead of testing first: the test's outcome is a coin toss
    where discs overlap, and its mispredictions cost more than the stores (20 % of a render)."""
    if s1 - s0 == 1:  # a one-pixel disc (offset 0, falloff 1, core): most far points
        if u >= 0 and u < width and v >= 0 and v < height:
            idx = v * width + u
            key = np.uint32(min(int(dist * falloff[s0] * 1000.0), MAX_DEPTH_MM) << 8) | \
                (lab | rim[s0])
            zb[idx] = min(key, zb[idx])
        return
    if u >= span and u < width - span and v >= span and v < height - span:
        base = v * width + u  # the whole disc is inside: no test per pixel
        for o in range(s0, s1):
            idx = base + linear[o]
            key = np.uint32(min(int(dist * falloff[o] * 1000.0), MAX_DEPTH_MM) << 8) | \
                (lab | rim[o])
            zb[idx] = min(key, zb[idx])
        return
    for o in range(s0, s1):
        uu = u + offsets[o, 0]
        vv = v + offsets[o, 1]
        if uu >= 0 and uu < width and vv >= 0 and vv < height:
            idx = vv * width + uu
            key = np.uint32(min(int(dist * falloff[o] * 1000.0), MAX_DEPTH_MM) << 8) | \
                (lab | rim[o])
            zb[idx] = min(key, zb[idx])


@numba.njit(cache=True, inline="always")
def _splat_value(zb, vb, val, u, v, dist, lab, s0, s1, span, offsets, linear, falloff, rim,
                 width, height):
    """:func:`_splat` that also keeps the point's value (its intensity code) where its key wins:
    a strict comparison, so of equal keys the first drawn keeps the pixel. Only with a value per
    point (the intensity cue on): the plain path keeps its plain min-stores."""
    if u >= span and u < width - span and v >= span and v < height - span:
        base = v * width + u  # the whole disc is inside: no test of the bounds per pixel
        for o in range(s0, s1):
            idx = base + linear[o]
            key = np.uint32(min(int(dist * falloff[o] * 1000.0), MAX_DEPTH_MM) << 8) | \
                (lab | rim[o])
            old = zb[idx]
            better = key < old  # selects, not a branch (equal keys: the first keeps it)
            zb[idx] = key if better else old
            vb[idx] = val if better else vb[idx]
        return
    for o in range(s0, s1):
        uu = u + offsets[o, 0]
        vv = v + offsets[o, 1]
        if uu >= 0 and uu < width and vv >= 0 and vv < height:
            idx = vv * width + uu
            key = np.uint32(min(int(dist * falloff[o] * 1000.0), MAX_DEPTH_MM) << 8) | \
                (lab | rim[o])
            old = zb[idx]
            better = key < old  # selects, not a branch (equal keys: the first keeps it)
            zb[idx] = key if better else old
            vb[idx] = val if better else vb[idx]


@numba.njit(cache=True, inline="always", error_model="numpy")
def _draw_chunks(zb, vb, values, first_chunk, chunk_step, coords, label, chunk_center,
                 chunk_radius, r, t, intr, dist_c, distorted, bounds, splat_lambda, lod_radius,
                 radius_max, near, far, offsets, linear, start, falloff, rim, width, height, model,
                 limit):
    """Chunks ``first_chunk``, ``first_chunk + chunk_step``, ... into the z-buffer ``zb``. Each
    visible chunk in two passes: its drawn points projected into scratch rows (vectorised),
    then their discs written. ``values`` (uint8 per point, or empty): the winning point's value
    is kept in ``vb`` too (the intensity cue)."""
    n = coords.shape[1]
    n_chunks = chunk_center.shape[0]
    fisheye = model == EQUIDISTANT
    rational = model == RATIONAL
    span_max = int(math.floor(radius_max))
    steps_max = int(math.floor(radius_max * RADIUS_STEPS))
    zb[:] = EMPTY_KEY
    with_values = values.shape[0] > 0
    if with_values:
        vb[:] = 255
    ok = np.empty(CHUNK, dtype=np.bool_)
    uf = np.empty(CHUNK, dtype=np.float64)
    vf = np.empty(CHUNK, dtype=np.float64)
    sf = np.empty(CHUNK, dtype=np.float64)
    ds = np.empty(CHUNK, dtype=np.float64)
    for ci in range(first_chunk, n_chunks, chunk_step):
        if fisheye:
            if not _chunk_visible_fisheye(chunk_center[ci], chunk_radius[ci], r, t, near,
                                          far, limit):
                continue
        elif not _chunk_visible(chunk_center[ci], chunk_radius[ci], r, t, near, far, bounds):
            continue
        stride = chunk_stride(chunk_center[ci], chunk_radius[ci], r, t, near, splat_lambda,
                              lod_radius)
        lam = splat_lambda * math.sqrt(np.float64(stride))
        first = ci * CHUNK
        m = drawn_count(stride, min(n - first, CHUNK))
        if fisheye:
            _project_fisheye(coords, first, m, r, t, intr, dist_c, lam, limit, near, far,
                             span_max, width, height, ok, uf, vf, sf, ds)
        else:
            _project_pinhole(coords, first, m, r, t, intr, dist_c, distorted, rational,
                             bounds, lam, limit, near, far, ok, uf, vf, sf, ds)
        for j in range(m):
            if not ok[j]:
                continue
            step = min(int(sf[j]), steps_max)
            if with_values:
                _splat_value(zb, vb, values[first + j], int(uf[j]), int(vf[j]), ds[j],
                             np.uint32(label[first + j]), start[step], start[step + 1],
                             step // RADIUS_STEPS, offsets, linear, falloff, rim, width, height)
                continue
            _splat(zb, int(uf[j]), int(vf[j]), ds[j], np.uint32(label[first + j]),
                   start[step], start[step + 1], step // RADIUS_STEPS, offsets, linear,
                   falloff, rim, width, height)


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _render_zbufs(coords, label, chunk_center, chunk_radius, r, t, intr, dist_c, distorted,
                  bounds, splat_lambda, lod_radius, radius_max, near, far, offsets, linear, start,
                  falloff, rim, width, height, n_threads, model, limit, values):
    """One z-buffer per thread (chunks dealt round-robin), not yet merged; with ``values``
    (not empty) a buffer per thread of the winning point's value too ((n_threads, 1) unused
    otherwise)."""
    zbufs = np.empty((n_threads, height * width), dtype=np.uint32)
    vbufs = np.empty((n_threads, height * width if values.shape[0] > 0 else 1), dtype=np.uint8)
    for th in numba.prange(n_threads):
        _draw_chunks(zbufs[th], vbufs[th], values, th, n_threads, coords, label, chunk_center,
                     chunk_radius, r, t, intr, dist_c, distorted, bounds, splat_lambda,
                     lod_radius, radius_max, near, far, offsets, linear, start, falloff, rim,
                     width, height, model, limit)
    return zbufs, vbufs


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _render_zbuf_serial(coords, label, chunk_center, chunk_radius, r, t, intr, dist_c,
                        distorted, bounds, splat_lambda, lod_radius, radius_max, near, far,
                        offsets, linear, start, falloff, rim, width, height, model, limit,
                        values):
    """The whole render into one z-buffer on the calling thread, no thread pool: what several
    renders running side by side on their own threads call (a frame set's frames,
    engine/frames.py, independent searches, engine/search.py), where one pool per render
    would fight the others for the cores. Compiled with ``parallel=True`` though nothing in it
    runs in parallel (numba finds no loop to split, so it uses no pool thread): numba's parallel
    pipeline compiles the same loops 4-8x faster than its plain one (bench street 1 M, one
    thread: 1/4 resolution 7.8 -> 1.0 ms, full resolution 21.5 -> 5.9 ms; the images identical),
    the same code the pooled kernel runs per thread; why the plain pipeline loses is not known."""
    zbufs = np.empty((1, height * width), dtype=np.uint32)
    vbufs = np.empty((1, height * width if values.shape[0] > 0 else 1), dtype=np.uint8)
    _draw_chunks(zbufs[0], vbufs[0], values, 0, 1, coords, label, chunk_center, chunk_radius, r,
                 t, intr, dist_c, distorted, bounds, splat_lambda, lod_radius, radius_max, near,
                 far, offsets, linear, start, falloff, rim, width, height, model, limit)
    return zbufs, vbufs


@numba.njit(cache=True, nogil=True)
def _merged_keys(zbufs):
    """The per-thread z-buffers' minimum, serially: a second parallel region costs more than it
    saves."""
    out = zbufs[0].copy()
    for th in range(1, zbufs.shape[0]):
        other = zbufs[th]
        for p in range(out.shape[0]):
            if other[p] < out[p]:
                out[p] = other[p]
    return out


@numba.njit(cache=True, nogil=True)
def _merged_labels(zbufs):
    """Merge and label extraction in one pass over the image (serial on purpose: waking the
    thread pool costs more than this loop)."""
    n_threads, size = zbufs.shape
    out = np.empty(size, dtype=np.uint8)
    for p in range(size):
        k = zbufs[0, p]
        for th in range(1, n_threads):
            if zbufs[th, p] < k:
                k = zbufs[th, p]
        out[p] = INVALID if k == EMPTY_KEY else np.uint8(k & 0xFF)
    return out


@numba.njit(cache=True, nogil=True)
def _merged_labels_keys(zbufs):
    """The merge of :func:`_merged_labels` that also keeps the merged keys (depth for the cues,
    engine/cues.py): one pass, so a cue costs no second render."""
    n_threads, size = zbufs.shape
    out = np.empty(size, dtype=np.uint8)
    keys = np.empty(size, dtype=np.uint32)
    for p in range(size):
        k = zbufs[0, p]
        for th in range(1, n_threads):
            if zbufs[th, p] < k:
                k = zbufs[th, p]
        keys[p] = k
        out[p] = INVALID if k == EMPTY_KEY else np.uint8(k & 0xFF)
    return out, keys


_NO_VALUES = np.empty(0, np.uint8)


@numba.njit(cache=True, nogil=True)
def _merged_labels_keys_values(zbufs, vbufs):
    """:func:`_merged_labels_keys` with the winning point's value per pixel (the first thread
    of equal keys; 255 where the label is INVALID: empty pixels and discs' rims)."""
    n_threads, size = zbufs.shape
    out = np.empty(size, dtype=np.uint8)
    keys = np.empty(size, dtype=np.uint32)
    vals = np.empty(size, dtype=np.uint8)
    for p in range(size):
        k = zbufs[0, p]
        best = 0
        for th in range(1, n_threads):
            if zbufs[th, p] < k:
                k = zbufs[th, p]
                best = th
        keys[p] = k
        lab = INVALID if k == EMPTY_KEY else np.uint8(k & 0xFF)
        out[p] = lab
        vals[p] = 255 if lab == INVALID else vbufs[best, p]
    return out, keys, vals


def _zbufs(pmap: PreparedMap, view: View, n_threads: int | None = None,
           values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The unmerged z-buffers and value buffers (used only with ``values``: the intensity cue);
    ``n_threads`` 1: on the calling thread (see :func:`_render_zbuf_serial`), else one per pool
    thread (default: numba's thread count)."""
    threads = n_threads or numba.get_num_threads()
    vals = _NO_VALUES if values is None else values
    if threads == 1:
        return _render_zbuf_serial(
            pmap.coords, pmap.label, pmap.chunk_center, pmap.chunk_radius, view.rotation,
            view.translation, view.intrinsics, view.distortion, view.distorted, view.bounds,
            view.splat_lambda, view.lod_radius, view.radius_max, view.near, view.far,
            view.disc_offsets, view.disc_linear, view.disc_start, view.disc_falloff,
            view.disc_rim, view.width, view.height, view.model, view.limit, vals)
    return _render_zbufs(
        pmap.coords, pmap.label, pmap.chunk_center, pmap.chunk_radius, view.rotation,
        view.translation, view.intrinsics, view.distortion, view.distorted, view.bounds,
        view.splat_lambda, view.lod_radius, view.radius_max, view.near, view.far,
        view.disc_offsets, view.disc_linear, view.disc_start, view.disc_falloff, view.disc_rim,
        view.width, view.height, threads, view.model, view.limit, vals)


def render_keys(pmap: PreparedMap, view: View, n_threads: int | None = None) -> np.ndarray:
    """The z-buffer (H, W) uint32, as reference.render_keys; EMPTY_KEY where nothing landed."""
    return _merged_keys(_zbufs(pmap, view, n_threads)[0]).reshape(view.height, view.width)


def render(pmap: PreparedMap, view: View, n_threads: int | None = None) -> np.ndarray:
    """Aligned label image (H, W) uint8, INVALID where no point landed."""
    return _merged_labels(_zbufs(pmap, view, n_threads)[0]).reshape(view.height, view.width)


def render_with_keys(pmap: PreparedMap, view: View, n_threads: int | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The label image of :func:`render` and the z-buffer of :func:`render_keys` from one render
    (what the cues need: depth is the z-buffer's upper 24 bits)."""
    labels, keys = _merged_labels_keys(_zbufs(pmap, view, n_threads)[0])
    return (labels.reshape(view.height, view.width), keys.reshape(view.height, view.width))


def render_with_values(pmap: PreparedMap, view: View, values: np.ndarray,
                       n_threads: int | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`render_with_keys` and, from the same render, the value (uint8 per stored point:
    the map's intensity codes) of the point that won each pixel; 255 where the label is
    INVALID (nothing drawn, or a disc's rim). As :func:`reference.render_values`, whose tie rule
    (the first drawn point of equal keys) it keeps with one thread."""
    values = np.ascontiguousarray(values, dtype=np.uint8)
    if values.shape != (len(pmap),):
        raise ValueError(f"{values.shape[0]} values for {len(pmap)} map points")
    labels, keys, vals = _merged_labels_keys_values(*_zbufs(pmap, view, n_threads, values))
    shape = (view.height, view.width)
    return labels.reshape(shape), keys.reshape(shape), vals.reshape(shape)
