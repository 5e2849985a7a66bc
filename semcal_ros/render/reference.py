"""Pure-numpy splat renderer: the readable definition the fast path must match pixel for pixel.

Each point becomes a disc of radius lambda / distance pixels (quantised, clipped); the z-buffer
holds one uint32 per pixel packing depth (mm, upper 24 bits) and label (lower 8 bits), so a single
minimum keeps the nearest point and breaks depth ties by label, deterministically.
"""

from __future__ import annotations

import numpy as np

from semcal_ros.camera import distort
from semcal_ros.labels import INVALID
from semcal_ros.render.lod import chunk_strides
from semcal_ros.render.prepare import CHUNK, PreparedMap
from semcal_ros.render.view import EMPTY_KEY, MAX_DEPTH_MM, RADIUS_STEPS, View


def project_points(pmap: PreparedMap, view: View) -> tuple[np.ndarray, ...]:
    """Pixel column, row, radius step, distance and label of every drawn point in view."""
    r, t = view.rotation, view.translation
    # level of detail: every k-th point of a chunk, its disc widened by sqrt(k) (see render/lod.py)
    stride = chunk_strides(pmap.chunk_center, pmap.chunk_radius, r, t, view.near,
                           view.splat_lambda, view.lod_radius)
    index = np.arange(len(pmap))
    point_stride = stride[index // CHUNK]
    drawn = (index % CHUNK) % point_stride == 0
    lam = view.splat_lambda * np.sqrt(point_stride[drawn].astype(np.float64))
    x = pmap.xyz[drawn, 0].astype(np.float64)
    y = pmap.xyz[drawn, 1].astype(np.float64)
    z = pmap.xyz[drawn, 2].astype(np.float64)
    label = pmap.label[drawn]
    xc = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
    yc = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
    zc = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
    dist = np.sqrt(xc * xc + yc * yc + zc * zc)
    keep = (zc > view.near) & (dist < view.far)
    xc, yc, zc, dist, lab, lam = xc[keep], yc[keep], zc[keep], dist[keep], label[keep], lam[keep]
    xn, yn = xc / zc, yc / zc
    xmin, xmax, ymin, ymax = view.bounds
    keep = (xn >= xmin) & (xn <= xmax) & (yn >= ymin) & (yn <= ymax)
    xn, yn, dist, lab, lam = xn[keep], yn[keep], dist[keep], lab[keep], lam[keep]
    k1, k2, p1, p2, k3 = view.distortion
    xd, yd = distort(xn, yn, k1, k2, p1, p2, k3) if view.distorted else (xn, yn)
    fx, fy, cx, cy = view.intrinsics
    u = np.floor(fx * xd + cx + 0.5).astype(np.int64)
    v = np.floor(fy * yd + cy + 0.5).astype(np.int64)
    steps_max = int(np.floor(view.radius_max * RADIUS_STEPS))
    step = np.minimum(np.floor(lam / dist * RADIUS_STEPS), steps_max).astype(np.int64)
    return u, v, step, dist, lab.astype(np.int64)


def render_keys(pmap: PreparedMap, view: View) -> np.ndarray:
    """The z-buffer (H, W) uint32; EMPTY_KEY where nothing landed."""
    u, v, step, dist, lab = project_points(pmap, view)
    w, h = view.width, view.height
    zbuf = np.full(h * w, EMPTY_KEY, dtype=np.uint32)
    for s in np.unique(step):
        sel = step == s
        us, vs, ds, ls = u[sel], v[sel], dist[sel], lab[sel]
        lo, hi = view.disc_start[s], view.disc_start[s + 1]
        for (du, dv), falloff, core in zip(view.disc_offsets[lo:hi], view.disc_falloff[lo:hi],
                                           view.disc_core[lo:hi]):
            uu, vv = us + du, vs + dv
            inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            depth_mm = np.minimum((ds[inside] * falloff * 1000.0).astype(np.int64), MAX_DEPTH_MM)
            key = ((depth_mm << 8) | (ls[inside] if core else INVALID)).astype(np.uint32)
            np.minimum.at(zbuf, vv[inside] * w + uu[inside], key)
    return zbuf.reshape(h, w)


def keys_to_labels(zbuf: np.ndarray) -> np.ndarray:
    labels = (zbuf & np.uint32(0xFF)).astype(np.uint8)
    labels[zbuf == EMPTY_KEY] = INVALID
    return labels


def render(pmap: PreparedMap, view: View) -> np.ndarray:
    """Aligned label image (H, W) uint8, INVALID where no point landed."""
    return keys_to_labels(render_keys(pmap, view))
