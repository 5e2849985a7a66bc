"""The geometric point labeller against SemanticKITTI's labels (KITTI 00 scans 1-2 by default:
scan 0 trains the labeller's forest), and on a synthetic scene's scans: per-class
precision/recall in the engine's aligned classes, the coarse classes of issue 33 and the time
per scan.

    .venv/bin/python benchmarks/geometric_labeller.py [--scene SCENE_DIR] [--repeats 3] [--stages]

Agreement is counted in the engine's aligned classes (semcal_ros.engine.labels: lane-marking = road,
parking = sidewalk, trunk = vegetation, ...), cars kept; a second table merges road and
sidewalk (the paper's KITTI set-up); a third counts coarse classes: ground (road, sidewalk,
terrain), building, vegetation (trunk included), pole (traffic signs on it included) and vehicle
(car and other vehicles), over the reference points of those five groups. Times: the median
of ``--repeats`` calls per scan after a warm-up call (numba/Open3D/Patchwork++ set-up is not
counted), wall and CPU (``time.process_time``: all threads of the process); the load average
is printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from semcal_ros.segmentation.geometric import coarse_agreement  # issue 33's coarse groups

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "kitti_odometry_00"


def coarse_table(pred: np.ndarray, ref: np.ndarray) -> str:
    """Recall and precision per coarse group; overall over the reference points in a group
    (:func:`semcal_ros.segmentation.geometric.coarse_agreement`)."""
    overall, groups = coarse_agreement(pred, ref)
    lines = ["| coarse class | reference points | precision | recall |", "|---|---|---|---|"]
    for name, (precision, recall, n_ref) in groups.items():
        lines.append(f"| {name} | {n_ref} | {100 * precision:.1f} % | {100 * recall:.1f} % |")
    lines.append(f"| **overall** | {sum(g[2] for g in groups.values())} | | "
                 f"**{100 * overall:.1f} %** |")
    return "\n".join(lines)


#: (module, function) pairs timed by ``--stages`` (nested: voxel_features holds the feature stages).
STAGES = (
    ("geometric", "estimate_ground_level"), ("geometric", "_ground_classes"),
    ("point_features", "_voxelize"), ("point_features", "nearest_voxels"),
    ("point_features", "_eigen_features"), ("point_features", "_column_features"),
    ("point_features", "_object_features"), ("point_features", "_ground_features"),
    ("geometric", "voxel_features"), ("forest", "_predict"), ("geometric", "smoothed_best"),
)


def stage_times(xyz: np.ndarray, intensity, repeats: int) -> tuple[dict, float, float]:
    """CPU and wall ms per call of each of :data:`STAGES` and of the whole ``label_scan``
    (mean of ``repeats`` calls after a warm-up), by wrapping each stage in a timer."""
    from semcal_ros.segmentation import forest, geometric, point_features

    modules = {"geometric": geometric, "point_features": point_features, "forest": forest}
    totals: dict[str, list[float]] = {}
    originals = []
    for mod_name, name in STAGES:
        module = modules[mod_name]
        original = getattr(module, name)
        originals.append((module, name, original))

        def timed(*args, _f=original, _name=name, **kwargs):
            wall, cpu = time.perf_counter(), time.process_time()
            out = _f(*args, **kwargs)
            acc = totals.setdefault(_name, [0.0, 0.0])
            acc[0] += time.process_time() - cpu
            acc[1] += time.perf_counter() - wall
            return out
        setattr(module, name, timed)
    try:
        geometric.label_scan(xyz, intensity)
        totals.clear()
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in range(repeats):
            geometric.label_scan(xyz, intensity)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    finally:
        for module, name, original in originals:
            setattr(module, name, original)
    per_call = {k: (1e3 * c / repeats, 1e3 * w / repeats) for k, (c, w) in totals.items()}
    return per_call, 1e3 * cpu / repeats, 1e3 * wall / repeats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--scans", default="1,2",
                    help="scans to label (0 trained the forest: held out are 1 and 2)")
    ap.add_argument("--scene", type=Path, help="a synthetic scene folder (semcal scene): its scans")
    ap.add_argument("--scene-scans", type=int, default=5, help="how many of the scene's scans")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-x", type=float,
                    help="count only KITTI points behind this x (m), e.g. -5 for a forest trained "
                         "with train_point_labeller.py --kitti-min-x 5")
    ap.add_argument("--stages", action="store_true",
                    help="also time each stage of label_scan on the first scan (CPU and wall ms)")
    args = ap.parse_args()

    from semcal_ros.io import kitti, ply
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.segmentation.geometric import label_scan, point_agreement

    preds, refs, times, cpus, sizes = [], [], [], [], []
    for i in (int(s) for s in args.scans.split(",")):
        cloud = kitti.read_scan(args.data / "velodyne" / f"{i:06d}.bin")
        ref = np.fromfile(args.data / "labels" / f"{i:06d}.label", np.uint32) & 0xFFFF
        intensity = cloud.extra.get("intensity")
        label_scan(cloud.xyz, intensity)  # warm-up
        runs, cpu = [], []
        for _ in range(args.repeats):
            start, cpu_start = time.perf_counter(), time.process_time()
            pred = label_scan(cloud.xyz, intensity)
            runs.append(time.perf_counter() - start)
            cpu.append(time.process_time() - cpu_start)
        keep = cloud.xyz[:, 0] < args.max_x if args.max_x is not None else slice(None)
        preds.append(pred[keep])
        refs.append(ref[keep])
        times.append(statistics.median(runs))
        cpus.append(statistics.median(cpu))
        sizes.append(len(pred))
        print(f"scan {i:06d}: {len(pred)} points, {1e3 * times[-1]:.0f} ms wall, "
              f"{1e3 * cpus[-1]:.0f} ms CPU (medians of {args.repeats}), load "
              f"{os.getloadavg()[0]:.2f}; overall "
              f"{100 * point_agreement(pred, ref).overall:.1f} %")
        if args.stages and len(times) == 1:
            stages, cpu_ms, wall_ms = stage_times(cloud.xyz, intensity, args.repeats)
            print(f"  stages (mean of {args.repeats} calls, load {os.getloadavg()[0]:.2f}): "
                  f"total {cpu_ms:.0f} ms CPU, {wall_ms:.0f} ms wall")
            for name, (c, w) in stages.items():
                print(f"    {name:24s} {c:6.0f} ms CPU {w:6.0f} ms wall")
    pred, ref = np.concatenate(preds), np.concatenate(refs)
    print(f"\nKITTI 00 scans {args.scans}: aligned classes, road / sidewalk / terrain apart")
    print(point_agreement(pred, ref).table())
    print("\nroad and sidewalk merged (the paper's KITTI set-up)")
    print(point_agreement(pred, ref, LabelMapping(dynamic=(), merge={"sidewalk": "road"}),
                          classes=("road", "terrain", "building", "fence", "vegetation", "pole",
                                   "traffic sign", "car")).table())
    print("\ncoarse classes (ground, building, vegetation, pole, vehicle)")
    print(coarse_table(pred, ref))
    print(f"\ntime per scan: {', '.join(f'{1e3 * t:.0f}' for t in times)} ms wall, "
          f"{', '.join(f'{1e3 * t:.0f}' for t in cpus)} ms CPU (all threads) for "
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
