"""The renderer against a plain numba splat renderer (issue 43 item 5), same view, same discs.

The plain renderer is what a study would write first: every point in one pass (transform,
distortion, pixel, disc size), its disc's pixels min-stored into a z-buffer per thread with a
bounds test per pixel, the threads' buffers merged; no chunks, no culling, no level of detail.
Both draw the same keys (depth in mm, label, the disc table's falloff and rim), and a min-store
does not depend on the order, so the two z-buffers must be equal: checked before timing.

The engine's renderer is timed with the level of detail off (every point drawn, as the plain
one draws them) and, for reference, on (what a calibration's full-resolution stage renders).
Interleaved, median of ``--repeats``; the ratio is what to quote.

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/render_plain.py \\
        --sizes 1000000,3500000 --repeats 30
"""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import replace

import numba
import numpy as np

from semcal_ros.engine.render import fast, prepare_map, view_for
from semcal_ros.engine.render.fast import _distort
from semcal_ros.engine.render.view import EMPTY_KEY, MAX_DEPTH_MM, RADIUS_STEPS, RenderParams
from semcal_tools.bench import median_ms
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world_of_size


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def plain_keys(xyz, label, r, t, intr, dc, bounds, lam, rmax, near, far, offsets, start, falloff,
               rim, width, height, n_threads, min_store):
    """Every point, one pass, a z-buffer per thread, merged: the plain splat renderer.
    ``min_store``: each disc pixel stores the minimum instead of testing first (no branch)."""
    n = xyz.shape[0]
    zbufs = np.empty((n_threads, height * width), dtype=np.uint32)
    steps_max = int(math.floor(rmax * RADIUS_STEPS))
    for th in numba.prange(n_threads):
        zb = zbufs[th]
        zb[:] = EMPTY_KEY
        for i in range(th * n // n_threads, (th + 1) * n // n_threads):
            x, y, z = np.float64(xyz[i, 0]), np.float64(xyz[i, 1]), np.float64(xyz[i, 2])
            xc = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
            yc = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
            zc = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
            if zc <= near:
                continue
            dist = math.sqrt(xc * xc + yc * yc + zc * zc)
            if dist >= far:
                continue
            xn, yn = xc / zc, yc / zc
            if xn < bounds[0] or xn > bounds[1] or yn < bounds[2] or yn > bounds[3]:
                continue
            xd, yd = _distort(xn, yn, dc[0], dc[1], dc[2], dc[3], dc[4])
            u = int(math.floor(intr[0] * xd + intr[2] + 0.5))
            v = int(math.floor(intr[1] * yd + intr[3] + 0.5))
            step = min(int(math.floor(lam / dist * RADIUS_STEPS)), steps_max)
            for o in range(start[step], start[step + 1]):
                uu, vv = u + offsets[o, 0], v + offsets[o, 1]
                if uu >= 0 and uu < width and vv >= 0 and vv < height:
                    key = np.uint32(min(int(dist * falloff[o] * 1000.0), MAX_DEPTH_MM) << 8) | \
                        (np.uint32(label[i]) | rim[o])
                    idx = vv * width + uu
                    if min_store:
                        zb[idx] = min(key, zb[idx])
                    elif key < zb[idx]:
                        zb[idx] = key
    out = zbufs[0].copy()
    for th in range(1, n_threads):
        for p in range(out.shape[0]):
            if zbufs[th, p] < out[p]:
                out[p] = zbufs[th, p]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1000000,3500000")
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    cam = camera()
    threads = numba.get_num_threads()
    print(f"{os.cpu_count()} CPUs, numba threads {threads}, load {os.getloadavg()[0]:.1f}, "
          f"{cam.width}x{cam.height}")
    for n in (int(s) for s in args.sizes.split(",") if s):
        pmap = prepare_map(street_world_of_size(n), center=GROUND_TRUTH.translation)
        lod_on = view_for(cam, GROUND_TRUTH, pmap, RenderParams())
        view = view_for(cam, GROUND_TRUTH, pmap, replace(RenderParams(), lod_radius=0.0))
        xyz = np.ascontiguousarray(pmap.xyz)

        def plain(min_store: bool = False) -> np.ndarray:
            return plain_keys(xyz, pmap.label, view.rotation, view.translation, view.intrinsics,
                              view.distortion, view.bounds, view.splat_lambda, view.radius_max,
                              view.near, view.far, view.disc_offsets, view.disc_start,
                              view.disc_falloff, view.disc_rim, view.width, view.height,
                              threads, min_store)

        ours = fast.render_keys(pmap, view).ravel()
        if not (np.array_equal(plain(), ours) and np.array_equal(plain(True), ours)):
            raise SystemExit(f"{n:,d} points: the plain renderer's z-buffer differs from the "
                             "engine's: not the same discs")
        rows = {"plain": [], "plain_min": [], "keys": [], "labels": [], "labels_lod": []}
        for _ in range(3):  # interleaved blocks
            rows["plain"].append(median_ms(plain, args.repeats))
            rows["plain_min"].append(median_ms(lambda: plain(True), args.repeats))
            rows["keys"].append(median_ms(lambda: fast.render_keys(pmap, view), args.repeats))
            rows["labels"].append(median_ms(lambda: fast.render(pmap, view), args.repeats))
            rows["labels_lod"].append(median_ms(lambda: fast.render(pmap, lod_on), args.repeats))
        m = {k: float(np.median(v)) for k, v in rows.items()}
        best = min(m["plain"], m["plain_min"])  # the faster plain renderer is the baseline
        print(f"{len(pmap):>9,d} points: plain {m['plain']:.2f} ms (min-stores "
              f"{m['plain_min']:.2f} ms); engine, every point: keys "
              f"{m['keys']:.2f} ms ({m['keys'] / best:.2f}x), labels {m['labels']:.2f} ms "
              f"({m['labels'] / best:.2f}x); level of detail on (a calibration's full "
              f"resolution): {m['labels_lod']:.2f} ms; load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
