"""Level of detail by screen footprint: how many of a chunk's points a view needs.

A lidar map is densest far from where its discs are large: beyond a few tens of metres a point's
disc shrinks below a pixel and many points land on each pixel, so most of a render's work is
redundant. For each chunk (1024 Morton-sorted points, spatially compact) the disc radius of its
nearest possible point decides a stride ``k``: only ceil(n / k) of its n points are drawn, with
their discs widened by sqrt(k) so the thinned surface still closes (k times fewer points spread
over the same area are sqrt(k) times farther apart). The drawn points are the first ceil(n / k) in
the chunk's stored, bit-reversed Morton order (render/prepare.py): every k-th point along the curve
when k is a power of two, an equally spread subset otherwise, read as one contiguous run (a strided
gather cost a cache miss per point: 1/4-resolution renders were memory-latency bound). Chunks whose
discs are at least ``lod_radius`` pixels keep every point. Both renderers call the same compiled
functions, so their images stay identical.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: never thin a chunk by more than this (a chunk then still draws 16 of its 1024 points)
MAX_STRIDE = 64


@numba.njit(cache=True, inline="always")
def chunk_stride(c, rad, r, t, near, splat_lambda, lod_radius):
    """Stride of one chunk (bounding sphere ``c``, ``rad`` in local map coordinates)."""
    if lod_radius <= 0.0:
        return 1
    xc = r[0, 0] * c[0] + r[0, 1] * c[1] + r[0, 2] * c[2] + t[0]
    yc = r[1, 0] * c[0] + r[1, 1] * c[1] + r[1, 2] * c[2] + t[1]
    zc = r[2, 0] * c[0] + r[2, 1] * c[1] + r[2, 2] * c[2] + t[2]
    nearest = max(math.sqrt(xc * xc + yc * yc + zc * zc) - rad, near)
    radius = splat_lambda / nearest
    if radius >= lod_radius:
        return 1
    ratio = lod_radius / radius
    return min(max(int(ratio * ratio), 1), MAX_STRIDE)


@numba.njit(cache=True)
def chunk_strides(chunk_center, chunk_radius, r, t, near, splat_lambda, lod_radius):
    """The stride of every chunk (the reference renderer's view of :func:`chunk_stride`)."""
    out = np.empty(chunk_center.shape[0], dtype=np.int64)
    for ci in range(chunk_center.shape[0]):
        out[ci] = chunk_stride(chunk_center[ci], chunk_radius[ci], r, t, near, splat_lambda,
                               lod_radius)
    return out


@numba.njit(cache=True, inline="always")
def drawn_count(stride, length):
    """How many of a chunk's ``length`` stored points a stride draws: the first ceil(length / k)."""
    return (length + stride - 1) // stride
