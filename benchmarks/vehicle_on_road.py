"""Would a vehicle-on-road rule find ours1's bus? For every object of a scan (the labeller's own
grouping: the 0.3 m occupancy grid's connected cells, told apart here by their object features)
with at least 30 points: its size, the share of its points labelled vegetation, its bottom above
the local ground, and the share of road (road, parking) among the labelled ground points within
1 m of its points; with SemanticKITTI's reference labels where the scan has them (``labels/`` beside
``velodyne/``). Prints the objects a rule "mostly vegetation, on the road, standing on the ground,
vehicle-sized: car" would relabel at each threshold (docs/segmentation.md, "A vehicle-on-road
rule, screened").

    .venv/bin/python benchmarks/vehicle_on_road.py SCAN [SCAN ...] [--all]

SCAN: a .bin (KITTI) or .pcd (PJLab) scan in the lidar's frame.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

VEHICLE = [10, 13, 18, 20, 252, 253, 254, 255, 256, 257, 258, 259]  # SemanticKITTI ids
VEGETATION = [70, 71, 72]  # vegetation, trunk, terrain
ROADS = [40, 44]  # road, parking
GROUND = [40, 44, 48, 49, 72]


def objects(path: Path) -> list[dict]:
    from scipy.spatial import cKDTree

    from semcal_ros.io import lidar_scans
    from semcal_ros.io.kitti import read_labels
    from semcal_ros.segmentation.geometric import label_scan, scan_features
    from semcal_ros.segmentation.point_features import FEATURE_NAMES

    reference = None
    labels_file = Path(str(path).replace("velodyne", "labels")).with_suffix(".label")
    if path.suffix == ".bin" and labels_file.is_file():
        reference = read_labels(labels_file)
    cloud = lidar_scans.read_lidar_scan(path)
    index, feats = scan_features(cloud.xyz, cloud.intensity)
    predicted = label_scan(cloud.xyz, cloud.intensity)[index]
    first = FEATURE_NAMES.index("obj_length")
    per_point = feats.values[feats.inverse]
    obj = per_point[:, first:first + 4]  # length, width, top, cells
    height = per_point[:, FEATURE_NAMES.index("height")]
    key = np.unique(np.round(obj, 3), axis=0, return_inverse=True)[1].ravel()
    pts = cloud.xyz[index]
    ground = np.isin(predicted, GROUND)
    tree, ground_labels = cKDTree(pts[ground, :2]), predicted[ground]
    rows = []
    for o in np.unique(key[obj[:, 3] > 0]):
        m = (key == o) & (obj[:, 3] > 0)
        n = int(m.sum())
        if n < 30:
            continue
        near = tree.query_ball_point(pts[m, :2][::max(1, n // 200)], 1.0)
        idx = np.unique(np.concatenate([np.asarray(i, int) for i in near]))
        row = {"n": n, "length": round(float(obj[m, 0][0]), 1),
               "width": round(float(obj[m, 1][0]), 1), "top": round(float(obj[m, 2][0]), 1),
               "vegetation": round(float(np.isin(predicted[m], VEGETATION).mean()), 2),
               "road_near": round(float(np.isin(ground_labels[idx], ROADS).mean()), 2)
               if len(idx) else None, "ground_near": len(idx),
               "bottom": round(float(np.percentile(height[m], 2)), 2),
               "centre": np.round(pts[m].mean(axis=0), 1).tolist()}
        if reference is not None:
            ref = reference[index][m]
            row["truth_vehicle"] = round(float(np.isin(ref, VEHICLE).mean()), 2)
            row["truth_vegetation"] = round(float(np.isin(ref, VEGETATION).mean()), 2)
        rows.append(row)
    return rows


def relabelled(row: dict, road: float, bottom: float) -> bool:
    """The rule screened: mostly vegetation, standing on the ground, vehicle-sized, on the road."""
    return (row["vegetation"] >= 0.5 and row["road_near"] is not None
            and row["road_near"] >= road and row["ground_near"] >= 10
            and row["bottom"] <= bottom and 1.0 <= row["top"] <= 4.5 and row["length"] >= 2.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scans", nargs="+", type=Path)
    ap.add_argument("--all", action="store_true", help="print every object, not only those "
                                                       "a rule would relabel")
    args = ap.parse_args()
    found = {path: objects(path) for path in args.scans}
    for path, rows in found.items():
        for row in rows:
            if args.all:
                print(path, json.dumps(row))
    for road in (0.5, 0.7):
        for bottom in (0.4, 0.8):
            hits = [(path, row) for path, rows in found.items() for row in rows
                    if relabelled(row, road, bottom)]
            print(f"road near >= {road}, bottom <= {bottom} m: {len(hits)} object(s)")
            for path, row in hits:
                print(f"  {path}: {json.dumps(row)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
