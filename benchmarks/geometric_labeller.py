"""The geometric point labeller against SemanticKITTI's labels (KITTI 00 scans 0-2), and on a
synthetic scene's scans: per-class precision/recall in the engine's aligned classes, and the
time per scan.

    .venv/bin/python benchmarks/geometric_labeller.py [--scene SCENE_DIR] [--repeats 3]

Agreement is counted in the engine's aligned classes (semcal_ros.engine.labels: lane-marking = road,
parking = sidewalk, trunk = vegetation, ...), cars kept; a second table merges road and
sidewalk (the paper's KITTI set-up). Times: the median of ``--repeats`` calls per scan after a
warm-up call (numba/Open3D/Patchwork++ set-up is not counted); the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "kitti_odometry_00"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--scans", default="0,1,2")
    ap.add_argument("--scene", type=Path, help="a synthetic scene folder (semcal scene): its scans")
    ap.add_argument("--scene-scans", type=int, default=5, help="how many of the scene's scans")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    from semcal_ros.io import kitti, ply
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.segmentation.geometric import label_scan, point_agreement

    preds, refs, times, sizes = [], [], [], []
    for i in (int(s) for s in args.scans.split(",")):
        cloud = kitti.read_scan(args.data / "velodyne" / f"{i:06d}.bin")
        ref = np.fromfile(args.data / "labels" / f"{i:06d}.label", np.uint32) & 0xFFFF
        intensity = cloud.extra.get("intensity")
        label_scan(cloud.xyz, intensity)  # warm-up
        runs = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            pred = label_scan(cloud.xyz, intensity)
            runs.append(time.perf_counter() - start)
        preds.append(pred)
        refs.append(ref)
        times.append(statistics.median(runs))
        sizes.append(len(pred))
        print(f"scan {i:06d}: {len(pred)} points, {1e3 * times[-1]:.0f} ms (median of "
              f"{args.repeats}), load {os.getloadavg()[0]:.2f}; overall "
              f"{100 * point_agreement(pred, ref).overall:.1f} %")
    pred, ref = np.concatenate(preds), np.concatenate(refs)
    print(f"\nKITTI 00 scans {args.scans}: aligned classes, road / sidewalk / terrain apart")
    print(point_agreement(pred, ref).table())
    print("\nroad and sidewalk merged (the paper's KITTI set-up)")
    print(point_agreement(pred, ref, LabelMapping(dynamic=(), merge={"sidewalk": "road"}),
                          classes=("road", "terrain", "building", "fence", "vegetation", "pole",
                                   "traffic sign", "car")).table())
    print(f"\ntime per scan: {', '.join(f'{1e3 * t:.0f}' for t in times)} ms for "
          f"{', '.join(str(n) for n in sizes)} points; load {os.getloadavg()}")

    if args.scene:
        files = sorted((args.scene / "scans").glob("*.ply"))[:: max(1, len(
            sorted((args.scene / "scans").glob("*.ply"))) // args.scene_scans)][:args.scene_scans]
        spreds, srefs = [], []
        for f in files:
            cloud = ply.read_ply(f)
            start = time.perf_counter()
            spreds.append(label_scan(cloud.xyz, cloud.extra.get("intensity")))
            srefs.append(cloud.label)
            print(f"{f.name}: {len(cloud)} points, {1e3 * (time.perf_counter() - start):.0f} ms")
        print(f"\n{args.scene}: {len(files)} scans")
        print(point_agreement(np.concatenate(spreds), np.concatenate(srefs)).table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
