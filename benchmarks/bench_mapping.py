"""Map building cost: seconds and peak memory for 50, 100 and 250 synthetic scans.

Target (issue 4): 250 scans of ~120k points into one map in <= 90 s and <= 4 GB peak on 2 cores.
The scans are a synthetic junction drive from the scene generator (88 lidar lines, which gives
~120k points per scan), generated once into a cache folder. Each size is built from the first N
scans by ``build_map`` with default parameters (d_max 60 m, 0.1 m map voxel, ICP on), in a fresh
process per run so that ``ru_maxrss`` is that run's peak (Open3D allocates outside Python, so
tracemalloc would miss most of it). Reading the PLY scans counts as part of the build.

    .venv/bin/python benchmarks/bench_mapping.py [--sizes 50 100 250] [--repeats 3]
        [--scene DIR] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

LINES = 88  # 128-line scans have ~174k points; 88 lines give the issue's ~120k
DEFAULT_SCENE = Path(os.environ.get("TMPDIR", "/tmp")) / f"semcal-bench-mapping-{LINES}l-250"


def ensure_scene(folder: Path, scans: int) -> Path:
    """The cached benchmark scene (generated when missing or too short).

    Generated in a child process: a child started by this one would otherwise inherit its
    peak memory in ``ru_maxrss`` (Linux keeps the high-water mark across fork + exec).
    """
    poses = folder / "scans" / "poses.yaml"
    if poses.is_file():
        from semcal_ros.io.scene_scans import read_scan_poses

        if len(read_scan_poses(poses)) >= scans:
            return folder
    print(f"generating {scans} scans into {folder} (once) ...", flush=True)
    start = time.perf_counter()
    code = ("import sys; from pathlib import Path; "
            "from semcal_tools.scenes.generate import SceneOptions, generate_scene; "
            "generate_scene(Path(sys.argv[1]), 'junction', 0, 'ideal', SceneOptions("
            "scans=int(sys.argv[2]), lines=int(sys.argv[3]), write_bag=False), force=True, "
            "progress=False)")
    subprocess.run([sys.executable, "-c", code, str(folder), str(scans), str(LINES)], check=True)
    print(f"  {time.perf_counter() - start:.0f} s", flush=True)
    return folder


def peak_rss_mb() -> tuple[float, float]:
    """(ru_maxrss, VmHWM) of this process in MB; VmHWM is this program's own high-water mark."""
    import resource

    hwm = 0.0
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            hwm = float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, hwm


def child(scene: Path, count: int) -> None:
    """One build in this process; prints one JSON line."""
    from semcal_ros.io.scene_scans import open_scene_scans
    from semcal_ros.mapping import MapBuildParams, ScanInput, build_map

    scans = open_scene_scans(scene)
    items = [ScanInput((lambda i=i: scans.scan(i)), scans.poses[i], scans.stamps[i], str(i))
             for i in range(count)]
    wall, cpu = time.perf_counter(), time.process_time()
    result = build_map(items, MapBuildParams())
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    peak_mb, hwm_mb = peak_rss_mb()
    print(json.dumps({"scans": count, "wall": wall, "cpu": cpu, "peak_mb": peak_mb,
                      "hwm_mb": hwm_mb,
                      "points_in": result.points_in, "map_points": len(result.map),
                      "pairs": len(result.pairs),
                      "rejected": sum(not p.accepted for p in result.pairs),
                      "timings": result.timings}))


def run_child(scene: Path, count: int, threads: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, __file__, "--child", str(count), "--scene", str(scene)],
                          capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"build of {count} scans failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 100, 250])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--threads", type=int, default=2, help="OMP_NUM_THREADS of the builds")
    parser.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.scene, args.child)
        return
    scene = ensure_scene(args.scene, max(args.sizes))
    load = os.getloadavg()[0]
    print(f"scene {scene}; {os.cpu_count()} cores, load average {load:.1f} before the runs "
          f"(a shared machine: other jobs slow the wall times)")
    rows = []
    for count in args.sizes:
        runs = [run_child(scene, count, args.threads) for _ in range(args.repeats)]
        wall = np.array([r["wall"] for r in runs])
        cpu = np.array([r["cpu"] for r in runs])
        peak = np.array([r["peak_mb"] for r in runs])
        last = runs[-1]
        rows.append((count, float(np.median(wall)), float(np.median(peak))))
        t = last["timings"]
        print(f"{count:4d} scans: wall median {np.median(wall):6.1f} s (min {wall.min():.1f}, "
              f"max {wall.max():.1f}), CPU {np.median(cpu):6.1f} s, peak RSS (ru_maxrss) "
              f"median {np.median(peak):6.0f} MB (max {peak.max():.0f}, VmHWM "
              f"{last['hwm_mb']:.0f}); "
              f"{last['points_in'] / count / 1e3:.0f}k points/scan in, map "
              f"{last['map_points'] / 1e6:.2f} M points; ICP pairs {last['pairs']} "
              f"({last['rejected']} rejected); last run: read {t['load']:.1f} s, filter+normals "
              f"{t['filter']:.1f} s, ICP {t['icp']:.1f} s, merge {t['merge']:.1f} s", flush=True)
    if len(rows) > 1:
        (n0, w0, m0), (n1, w1, m1) = rows[0], rows[-1]
        print(f"growth {n0} -> {n1} scans ({n1 / n0:.1f}x): time {w1 / w0:.2f}x "
              f"({w0 / n0 * 1e3:.0f} -> {w1 / n1 * 1e3:.0f} ms per scan), peak memory "
              f"{m1 / m0:.2f}x ({m0:.0f} -> {m1:.0f} MB)")
    for count, wall, peak in rows:
        if count == 250:
            print(f"target 250 scans <= 90 s and <= 4096 MB: {wall:.1f} s, {peak:.0f} MB -> "
                  f"{'met' if wall <= 90 and peak <= 4096 else 'NOT met'}")


if __name__ == "__main__":
    main()
