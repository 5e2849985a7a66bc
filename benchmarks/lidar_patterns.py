"""The geometric point labeller on other lidars: held-out SemanticKITTI scans (KITTI 00 scans
1-2; scan 0 trains the forest) resampled to other beam patterns, mounting heights and intensity
scales (``semcal_tools.lidar_patterns.TEST_PATTERNS``), against their SemanticKITTI labels.

    .venv/bin/python benchmarks/lidar_patterns.py [--model M.npz] [--scans 1,2] [--max-x -5]

Per pattern: points, coarse accuracy (ground, building, vegetation, pole, vehicle: issue 33's
groups), building recall, the worst coarse group's recall, and the aligned classes apart
(overall and the worst class with more than ``--min-points`` reference points). Issue 41's
targets: coarse >= 90 %, building >= 85 %, no class below 70 %. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "kitti_odometry_00"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--scans", default="1,2")
    ap.add_argument("--model", type=Path, help="forest file (default: the shipped one)")
    ap.add_argument("--patterns", help="comma-separated indices of TEST_PATTERNS (default: all)")
    ap.add_argument("--max-x", type=float,
                    help="count only points behind this x (m, KITTI's frame), e.g. -5 for a "
                         "forest trained with train_point_labeller.py --kitti-min-x 5")
    ap.add_argument("--min-points", type=int, default=1000,
                    help="aligned classes with fewer reference points are not the 'worst'")
    args = ap.parse_args()

    from semcal_ros.io import kitti
    from semcal_ros.segmentation.geometric import coarse_agreement, label_scan, point_agreement
    from semcal_tools.lidar_patterns import KITTI_HEIGHT, TEST_PATTERNS, resample

    patterns = TEST_PATTERNS if not args.patterns else \
        [TEST_PATTERNS[int(i)] for i in args.patterns.split(",")]
    scans = []
    for i in (int(s) for s in args.scans.split(",")):
        cloud = kitti.read_scan(args.data / "velodyne" / f"{i:06d}.bin")
        ref = (np.fromfile(args.data / "labels" / f"{i:06d}.label", np.uint32) & 0xFFFF
               ).astype(np.uint16)
        scans.append((cloud.xyz, ref, cloud.extra.get("intensity")))
    print(f"model {args.model or 'shipped'}; KITTI 00 scans {args.scans}"
          + (f", points with x < {args.max_x} m" if args.max_x is not None else "")
          + f"; load {os.getloadavg()[0]:.2f}")
    print("| pattern | points per scan | coarse | building | worst coarse class | classes apart | "
          "worst class apart |")
    print("|---|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    for pattern in patterns:
        preds, refs, sizes = [], [], []
        for xyz, ref, intensity in scans:
            pts, lab, inten = resample(xyz, ref, intensity, pattern)
            pred = label_scan(pts, inten, model=args.model)
            if args.max_x is not None:
                keep = pts[:, 0] < args.max_x
                pred, lab = pred[keep], lab[keep]
            preds.append(pred)
            refs.append(lab)
            sizes.append(len(pts))
        pred, ref = np.concatenate(preds), np.concatenate(refs)
        coarse, groups = coarse_agreement(pred, ref)
        worst = min(groups, key=lambda g: groups[g][1])
        fine = point_agreement(pred, ref)
        rows = {n: v for n, v in fine.per_class.items() if v[2] >= args.min_points}
        worst_fine = min(rows, key=lambda n: rows[n][1])
        print(f"| {pattern.name} | {int(np.mean(sizes))} | {100 * coarse:.1f} % | "
              f"{100 * groups['building'][1]:.1f} % | {worst} {100 * groups[worst][1]:.1f} % | "
              f"{100 * fine.overall:.1f} % | {worst_fine} {100 * rows[worst_fine][1]:.1f} % |")
        sys.stdout.flush()
    print(f"\n{len(patterns)} patterns x {len(scans)} scans in {time.perf_counter() - t0:.0f} s; "
          f"KITTI's own height {KITTI_HEIGHT} m; load {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
