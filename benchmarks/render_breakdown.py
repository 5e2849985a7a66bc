"""Where a render's time goes (issue 19): the fast path beside variants of its own loop that stop
early, on the bench street and on scene folders, interleaved in one run (ratios hold on a loaded
machine, absolute times do not).

Variants, each one thread, same chunks, culling and level of detail as ``render/fast.py``:
  loads       read the drawn points only (memory)
  project     + transform, cull, distort, pixel and disc size (no z-buffer)
  per_offset  + every disc pixel through the generic per-offset loop with bounds tests (the
              renderer before issue 19's one-pixel and inside-the-image paths)
  fast_1t / fast_2t   render_keys with one / two threads (merge included)
  render_2t   fast.render: two threads, merge and label extraction fused

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/render_breakdown.py \\
        --sizes 1000000,3500000 --scenes /work/catalogue/junction-ideal --repeats 15
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numba
import numpy as np

from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.render import fast, reference
from semcal_ros.engine.render.fast import _chunk_visible, _distort
from semcal_ros.engine.render.lod import chunk_stride, drawn_count
from semcal_ros.engine.render.prepare import CHUNK
from semcal_ros.engine.render.view import EMPTY_KEY, MAX_DEPTH_MM, RADIUS_STEPS

LOADS, PROJECT, PER_OFFSET = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def _variant(xyz, label, cc, cr, r, t, intr, dc, bounds, lam0, lod, rmax, near, far, offsets,
             start, falloff, core, width, height, mode):
    """The pinhole/plumb_bob path of fast._render_zbufs, one thread, cut at ``mode``."""
    n = xyz.shape[0]
    zb = np.empty(height * width, dtype=np.uint32)
    zb[:] = EMPTY_KEY
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dc[0], dc[1], dc[2], dc[3], dc[4]
    xmin, xmax, ymin, ymax = bounds[0], bounds[1], bounds[2], bounds[3]
    steps_max = int(math.floor(rmax * RADIUS_STEPS))
    acc = 0.0
    visited = 0
    drawn = 0
    writes = 0
    for ci in range(cc.shape[0]):
        if not _chunk_visible(cc[ci], cr[ci], r, t, near, far, bounds):
            continue
        stride = chunk_stride(cc[ci], cr[ci], r, t, near, lam0, lod)
        lam = lam0 * math.sqrt(np.float64(stride))
        first = ci * CHUNK
        for i in range(first, first + drawn_count(stride, min(n - first, CHUNK))):
            visited += 1
            x = np.float64(xyz[i, 0])
            y = np.float64(xyz[i, 1])
            z = np.float64(xyz[i, 2])
            if mode == LOADS:
                acc += x + y + z
                continue
            xc = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
            yc = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
            zc = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
            dist = math.sqrt(xc * xc + yc * yc + zc * zc)
            if not (zc > near and dist < far):
                continue
            xn = xc / zc
            yn = yc / zc
            if not (xn >= xmin and xn <= xmax and yn >= ymin and yn <= ymax):
                continue
            xd, yd = _distort(xn, yn, k1, k2, p1, p2, k3)
            u = int(math.floor(fx * xd + cx + 0.5))
            v = int(math.floor(fy * yd + cy + 0.5))
            step = min(int(math.floor(lam / dist * RADIUS_STEPS)), steps_max)
            drawn += 1
            writes += start[step + 1] - start[step]
            if mode == PROJECT:
                acc += u + v + step
                continue
            lab = label[i]
            for o in range(start[step], start[step + 1]):
                uu = u + offsets[o, 0]
                vv = v + offsets[o, 1]
                if uu >= 0 and uu < width and vv >= 0 and vv < height:
                    idx = vv * width + uu
                    key = np.uint32((min(int(dist * falloff[o] * 1000.0), MAX_DEPTH_MM) << 8) |
                                    (lab | core[o]))
                    if key < zb[idx]:
                        zb[idx] = key
    return zb, acc, visited, drawn, writes


def _args(pmap, v, mode):
    return (pmap.xyz, pmap.label, pmap.chunk_center, pmap.chunk_radius, v.rotation,
            v.translation, v.intrinsics, v.distortion, v.bounds, v.splat_lambda, v.lod_radius,
            v.radius_max, v.near, v.far, v.disc_offsets, v.disc_start, v.disc_falloff,
            v.disc_rim, v.width, v.height, mode)


def breakdown(name: str, problem: Problem, pose, repeats: int) -> None:
    pmap = problem.pmap
    for stage in range(len(problem.stages)):
        view = problem.level(stage).setup.view(pose)
        if view.model != 0:
            print(f"{name}: not a plumb_bob camera, skipped")
            return
        zb, _, visited, drawn, writes = _variant(*_args(pmap, view, PER_OFFSET))
        # the cut-short loop is the renderer's own arithmetic: same image
        assert np.array_equal(zb, reference.render_keys(pmap, view).ravel())
        variants = {
            "loads": lambda: _variant(*_args(pmap, view, LOADS)),
            "project": lambda: _variant(*_args(pmap, view, PROJECT)),
            "per_offset": lambda: _variant(*_args(pmap, view, PER_OFFSET)),
            "fast_1t": lambda: fast.render_keys(pmap, view, 1),
            "fast_2t": lambda: fast.render_keys(pmap, view, 2),
            "render_2t": lambda: fast.render(pmap, view, 2),
        }
        times = {k: [] for k in variants}
        for fn in variants.values():
            fn()
        for _ in range(repeats):
            for k, fn in variants.items():
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
        covered = int((zb != EMPTY_KEY).sum())
        print(f"{name} 1/{problem.stages[stage].scale}: {len(pmap):,d} points, {visited:,d} read, "
              f"{drawn:,d} drawn, {writes:,d} disc pixels ({writes / max(covered, 1):.1f} per "
              f"covered pixel); " + ", ".join(f"{k} {np.median(v) * 1e3:.2f} ms"
                                              for k, v in times.items())
              + f"; load {os.getloadavg()[0]:.1f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000000", help="bench street sizes ('' for none)")
    ap.add_argument("--scenes", nargs="*", default=[], help="scene folders (truth pose)")
    ap.add_argument("--repeats", type=int, default=15)
    a = ap.parse_args()
    from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world_of_size, target_image

    print(f"load {os.getloadavg()[0]:.1f}, numba threads {numba.get_num_threads()}")
    cam = camera()
    for n in [int(s) for s in a.sizes.split(",") if s]:
        problem = Problem(street_world_of_size(n), target_image(cam), cam,
                          GROUND_TRUTH.translation, CalibrationParams())
        breakdown(f"bench street {n // 1000}k", problem, GROUND_TRUTH, a.repeats)
    for folder in a.scenes:
        from pathlib import Path

        from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
        from semcal_ros.io.ply import read_ply

        d = Path(folder)
        truth = read_pose(d / "ground_truth.yaml")
        problem = Problem(read_ply(d / "map.ply"), read_label_image(d / "labels.png"),
                          read_camera_info(d / "camera_info.yaml"), truth.translation)
        breakdown(d.name, problem, truth, a.repeats)


if __name__ == "__main__":
    main()
