"""Pure-numpy splat renderer: the readable definition the fast path must match pixel for pixel.

Each point becomes a disc of radius lambda / distance pixels (quantised, clipped); the z-buffer
holds one uint32 per pixel packing depth (mm, upper 24 bits) and label (lower 8 bits), so a single
minimum keeps the nearest point and breaks depth ties by label, deterministically.

Depth is the range (distance to the camera centre), never z, and the disc radius follows the
range too: both stay meaningful for a fisheye, whose points beside or behind the image plane have
z <= 0. Culling is per model: pinhole models drop z <= near and points outside the undistorted
image box (rational_polynomial also beyond its fold radius); the equidistant model drops ranges
<= near and rays more than ``view.limit`` from the optical axis (camera.render_limit).
"""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.camera import MODEL_ID, distort, distort_rational, equidistant_many
from semcal_ros.engine.labels import INVALID
from semcal_ros.engine.render.lod import chunk_strides
from semcal_ros.engine.render.prepare import CHUNK, PreparedMap
from semcal_ros.engine.render.view import EMPTY_KEY, MAX_DEPTH_MM, RADIUS_STEPS, View

RATIONAL = MODEL_ID["rational_polynomial"]
EQUIDISTANT = MODEL_ID["equidistant"]


def project_points(pmap: PreparedMap, view: View, with_index: bool = False
                   ) -> tuple[np.ndarray, ...]:
    """Pixel column, row, radius step, distance and label of every drawn point in view (and,
    ``with_index``, its stored index)."""
    r, t = view.rotation, view.translation
    # level of detail: the first ceil(n/k) stored points of a chunk, discs widened by sqrt(k)
    # (render/lod.py)
    stride = chunk_strides(pmap.chunk_center, pmap.chunk_radius, r, t, view.near,
                           view.splat_lambda, view.lod_radius)
    index = np.arange(len(pmap))
    chunk = index // CHUNK
    point_stride = stride[chunk]
    length = np.minimum(CHUNK, len(pmap) - chunk * CHUNK)
    drawn = (index % CHUNK) < (length + point_stride - 1) // point_stride  # lod.drawn_count
    lam = view.splat_lambda * np.sqrt(point_stride[drawn].astype(np.float64))
    x = pmap.xyz[drawn, 0].astype(np.float64)
    y = pmap.xyz[drawn, 1].astype(np.float64)
    z = pmap.xyz[drawn, 2].astype(np.float64)
    label = pmap.label[drawn]
    if with_index:  # the stored index rides in the label's place through the culls below
        label = np.flatnonzero(drawn) * 256 + label.astype(np.int64)
    xc = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
    yc = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
    zc = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
    dist = np.sqrt(xc * xc + yc * yc + zc * zc)
    if view.model == EQUIDISTANT:
        # a fisheye sees beside and behind its image plane: near and far are ranges, the field
        # is bounded by the ray's angle to the optical axis (camera.render_limit)
        keep = (dist > view.near) & (dist < view.far)
        xc, yc, zc, dist, lab, lam = xc[keep], yc[keep], zc[keep], dist[keep], label[keep], lam[keep]
        xd, yd, theta = equidistant_many(xc, yc, zc, view.distortion[:4].copy())
        keep = theta <= view.limit
        xd, yd, dist, lab, lam = xd[keep], yd[keep], dist[keep], lab[keep], lam[keep]
    else:
        keep = (zc > view.near) & (dist < view.far)
        xc, yc, zc, dist, lab, lam = xc[keep], yc[keep], zc[keep], dist[keep], label[keep], lam[keep]
        xn, yn = xc / zc, yc / zc
        xmin, xmax, ymin, ymax = view.bounds
        keep = (xn >= xmin) & (xn <= xmax) & (yn >= ymin) & (yn <= ymax)
        if view.model == RATIONAL:
            keep &= xn * xn + yn * yn <= view.limit
        xn, yn, dist, lab, lam = xn[keep], yn[keep], dist[keep], lab[keep], lam[keep]
        if view.model == RATIONAL:
            xd, yd = distort_rational(xn, yn, *view.distortion)
        elif view.distorted:
            xd, yd = distort(xn, yn, *view.distortion[:5])
        else:
            xd, yd = xn, yn
    fx, fy, cx, cy = view.intrinsics
    u = np.floor(fx * xd + cx + 0.5).astype(np.int64)
    v = np.floor(fy * yd + cy + 0.5).astype(np.int64)
    if view.model == EQUIDISTANT:  # off-image centres whose discs cannot reach the image
        span = int(np.floor(view.radius_max))
        keep = (u >= -span) & (u < view.width + span) & (v >= -span) & (v < view.height + span)
        u, v, dist, lab, lam = u[keep], v[keep], dist[keep], lab[keep], lam[keep]
    steps_max = int(np.floor(view.radius_max * RADIUS_STEPS))
    step = np.minimum(np.floor(lam / dist * RADIUS_STEPS), steps_max).astype(np.int64)
    lab = lab.astype(np.int64)
    if with_index:
        return u, v, step, dist, lab & 0xFF, lab >> 8
    return u, v, step, dist, lab


def _disc_writes(u, v, step, dist, lab, view: View, *extra):
    """Every disc pixel the projected points write, one disc offset at a time: (pixel index,
    key, and the points' ``extra`` arrays) for the points whose pixel lies in the image."""
    w, h = view.width, view.height
    for s in np.unique(step):
        sel = step == s
        us, vs, ds, ls = u[sel], v[sel], dist[sel], lab[sel]
        more = [e[sel] for e in extra]
        lo, hi = view.disc_start[s], view.disc_start[s + 1]
        for (du, dv), falloff, rim in zip(view.disc_offsets[lo:hi], view.disc_falloff[lo:hi],
                                          view.disc_rim[lo:hi].astype(np.int64)):
            uu, vv = us + du, vs + dv
            inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            depth_mm = np.minimum((ds[inside] * falloff * 1000.0).astype(np.int64), MAX_DEPTH_MM)
            key = ((depth_mm << 8) | ls[inside] | rim).astype(np.uint32)  # rim: label INVALID
            yield (vv[inside] * w + uu[inside], key, *[m[inside] for m in more])


def render_keys(pmap: PreparedMap, view: View) -> np.ndarray:
    """The z-buffer (H, W) uint32; EMPTY_KEY where nothing landed."""
    zbuf = np.full(view.height * view.width, EMPTY_KEY, dtype=np.uint32)
    u, v, step, dist, lab = project_points(pmap, view)
    for idx, key in _disc_writes(u, v, step, dist, lab, view):
        np.minimum.at(zbuf, idx, key)
    return zbuf.reshape(view.height, view.width)


def keys_to_labels(zbuf: np.ndarray) -> np.ndarray:
    labels = (zbuf & np.uint32(0xFF)).astype(np.uint8)
    labels[zbuf == EMPTY_KEY] = INVALID
    return labels


def render(pmap: PreparedMap, view: View) -> np.ndarray:
    """Aligned label image (H, W) uint8, INVALID where no point landed."""
    return keys_to_labels(render_keys(pmap, view))


def render_values(pmap: PreparedMap, view: View, values: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The z-buffer and, per pixel, the value (one per stored point: the map's intensity
    codes) of the point whose key won it: of several with that key, the first drawn (lowest
    stored index); 255 where the label is INVALID (nothing drawn, or a disc's rim)."""
    zbuf = render_keys(pmap, view).ravel()
    u, v, step, dist, lab, index = project_points(pmap, view, with_index=True)
    w, h = view.width, view.height
    first = np.full(h * w, np.iinfo(np.int64).max, np.int64)
    for idx, key, ix in _disc_writes(u, v, step, dist, lab, view, index):
        wins = key == zbuf[idx]
        np.minimum.at(first, idx[wins], ix[wins])
    out = np.full(h * w, 255, np.uint8)
    ok = (keys_to_labels(zbuf) != INVALID) & (first < len(pmap))
    out[ok] = np.asarray(values, np.uint8)[first[ok]]
    return zbuf.reshape(h, w), out.reshape(h, w)
