"""Render time of one map through each lens model, as ratios taken within one run (docs/lenses.md).

The same prepared map and pose are rendered through plumb_bob (the engine's 90 deg synthetic
camera with barrel distortion), rational_polynomial (120 deg) and equidistant (185 deg), with the
engine's render parameters (level of detail on) and every point drawn; renders of the three
models are interleaved so machine load hits them alike. A wider lens sees more of the map, so
the time per million points *drawn* (after culling and level of detail) is printed too.

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/bench_lens.py --points 1000000
    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/bench_lens.py --scene SCENE_DIR
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.render.view import RenderParams
from semcal_ros.engine.render import fast, prepare_map, reference, view_for
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world_of_size


def lenses() -> dict[str, CameraModel]:
    return {"plumb_bob": camera(),
            "rational_polynomial": CameraModel.rational_fov(960, 600, 120.0),
            "equidistant": CameraModel.fisheye_fov(960, 600, 185.0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000, help="bench street size")
    ap.add_argument("--scene", type=Path, help="use a scene folder's map and ground truth instead")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    if args.scene:
        from semcal_ros.io.files import read_pose
        from semcal_ros.io.ply import read_ply

        cloud, pose = read_ply(args.scene / "map.ply"), read_pose(args.scene / "ground_truth.yaml")
        rp0 = RenderParams()
        pmap = prepare_map(cloud, center=pose.translation, radius=rp0.crop_radius or None)
        where = f"scene {args.scene.name}"
    else:
        pmap = prepare_map(street_world_of_size(args.points), center=GROUND_TRUTH.translation)
        pose, where = GROUND_TRUTH, "bench street"
    print(f"{where}: {len(pmap):,d} points, 960x600, load {os.getloadavg()[0]:.2f} at start")
    rp = RenderParams()
    cams = lenses()
    rows = {}
    for mode, params in (("level of detail", rp), ("every point", replace(rp, lod_radius=0.0))):
        views = {name: view_for(cam, pose, pmap, params) for name, cam in cams.items()}
        for v in views.values():
            fast.render(pmap, v)  # compile / warm up
        times: dict[str, list[float]] = {name: [] for name in cams}
        for _ in range(args.repeats):
            for name, v in views.items():
                t0 = time.perf_counter()
                fast.render(pmap, v)
                times[name].append(time.perf_counter() - t0)
        base = float(np.median(times["plumb_bob"]))
        for name, v in views.items():
            ms = float(np.median(times[name])) * 1000.0
            drawn = len(reference.project_points(pmap, v)[0])
            per_m = ms / (len(pmap) / 1e6)
            rows[(mode, name)] = ms
            print(f"{mode:15s} {name:20s} {ms:7.2f} ms  ({per_m:6.2f} ms per 1 M map points, "
                  f"ratio to plumb_bob {ms / 1000.0 / base:4.2f}; {drawn:,d} drawn, "
                  f"{ms / max(drawn, 1) * 1e6:6.2f} ms per 1 M drawn)")
    print(f"load {os.getloadavg()[0]:.2f} at end")


if __name__ == "__main__":
    main()
