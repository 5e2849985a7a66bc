"""Map building cost: seconds, stage shares and peak memory for N synthetic scans; A/B vs a commit.

The scans are a synthetic junction drive from the scene generator (88 lidar lines, ~125k points
per scan), generated once into a cache folder. Each size is built from the first N scans by
``build_map`` with default parameters (d_max 60 m, 0.1 m map voxel, ICP on) and de-skew on
(``--deskew azimuth``: the synthetic sweeps are instantaneous, so de-skew moves nothing that
matters here, but its cost is counted), in a fresh process per run so that ``ru_maxrss`` is that
run's peak (Open3D allocates outside Python, so tracemalloc would miss most of it). Reading the
PLY scans counts as part of the build. Each run prints its stages' shares.

``--baseline REF`` builds the same scans with commit REF too: REF is checked out once into a
``git worktree`` under /tmp and its builder runs in a separate process with PYTHONPATH on that
worktree (older commits have another module layout; this script's child only imports
``semcal_ros.io.scene_scans`` and ``semcal_ros.mapping``, present in all of them). The two
builders run alternately (A B A B ...), and the wall-time ratio A/B is taken pair by pair, so a
drift of the shared machine's speed moves both runs of a pair.

    .venv/bin/python benchmarks/bench_mapping.py [--sizes 50 100 250] [--repeats 3]
        [--scene DIR] [--threads 2] [--deskew azimuth|field|none] [--baseline 8f45d66]
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
REPO = Path(__file__).resolve().parents[1]
#: stage timing keys in the order they are printed (older builders report a subset)
STAGES = ("load", "deskew", "filter", "grids", "covariances", "icp", "merge")


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


def child(scene: Path, count: int, deskew: str) -> None:
    """One build in this process (whatever ``semcal_ros`` is on the path); prints one JSON line."""
    import semcal_ros
    from semcal_ros.io.scene_scans import open_scene_scans
    from semcal_ros.mapping import MapBuildParams, ScanInput, build_map

    scans = open_scene_scans(scene)
    items = [ScanInput((lambda i=i: scans.scan(i)), scans.poses[i], scans.stamps[i], str(i))
             for i in range(count)]
    params = MapBuildParams()
    has_deskew = hasattr(params, "deskew")  # builders before de-skew existed have none
    if has_deskew:
        params.deskew.source = deskew
        params.deskew.enabled = deskew != "none"
    wall, cpu = time.perf_counter(), time.process_time()
    result = build_map(items, params)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    peak_mb, hwm_mb = peak_rss_mb()
    print(json.dumps({"scans": count, "wall": wall, "cpu": cpu, "peak_mb": peak_mb,
                      "hwm_mb": hwm_mb, "source": str(Path(semcal_ros.__file__).parents[1]),
                      "deskew": deskew if has_deskew else "absent",
                      "points_in": result.points_in, "map_points": len(result.map),
                      "pairs": len(result.pairs),
                      "rejected": sum(not p.accepted for p in result.pairs),
                      "timings": result.timings}))


def baseline_tree(ref: str) -> Path:
    """A worktree of ``ref`` under /tmp (created once, reused while its commit matches)."""
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", f"{ref}^{{commit}}"],
                            capture_output=True, text=True)
    if commit.returncode != 0:
        raise SystemExit(f"--baseline {ref}: not a commit of {REPO}")
    sha = commit.stdout.strip()
    tree = Path(os.environ.get("TMPDIR", "/tmp")) / f"semcal-bench-baseline-{sha[:12]}"
    if not (tree / "semcal_ros" / "mapping").is_dir():
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), sha],
                       check=True, capture_output=True)
    return tree


def run_child(scene: Path, count: int, threads: int, deskew: str,
              source: Path | None = None) -> dict:
    """One build in a fresh process; ``source`` puts another checkout's semcal_ros first."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), OPENBLAS_NUM_THREADS="1")
    if source is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(source)] + [p for p in env.get(
            "PYTHONPATH", "").split(os.pathsep) if p])
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(count),
                           "--scene", str(scene), "--deskew", deskew],
                          capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"build of {count} scans failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def stage_line(timings: dict) -> str:
    """Each stage's seconds and share of the stages' sum. The builder reads and prepares the
    next scan, and voxelizes merged groups, in threads beside registration, so the sum may
    exceed the wall time (``total``)."""
    total = timings.get("total", 0.0)
    known = {k: timings[k] for k in STAGES if k in timings}
    work = sum(known.values())
    parts = [f"{k} {v:.1f} s ({100 * v / max(work, 1e-9):.0f} %)" for k, v in known.items()]
    return (f"stages sum {work:.1f} s in {total:.1f} s of wall time: " + ", ".join(parts))


def describe(label: str, runs: list[dict]) -> str:
    wall = np.array([r["wall"] for r in runs])
    cpu = np.array([r["cpu"] for r in runs])
    peak = np.array([r["peak_mb"] for r in runs])
    last = runs[-1]
    count = last["scans"]
    return (f"{label}{count:4d} scans: wall median {np.median(wall):6.1f} s (min {wall.min():.1f}, "
            f"max {wall.max():.1f}), CPU {np.median(cpu):6.1f} s, peak RSS median "
            f"{np.median(peak):6.0f} MB (max {peak.max():.0f}); "
            f"{last['points_in'] / count / 1e3:.0f}k points/scan in, map "
            f"{last['map_points'] / 1e6:.2f} M points; ICP pairs {last['pairs']} "
            f"({last['rejected']} rejected); de-skew {last['deskew']}\n"
            f"      last run {stage_line(last['timings'])}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 100, 250])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--threads", type=int, default=2, help="OMP_NUM_THREADS of the builds")
    parser.add_argument("--deskew", choices=("azimuth", "field", "auto", "none"),
                        default="azimuth", help="de-skew source of the builds (azimuth: on "
                        "for every scan)")
    parser.add_argument("--baseline", metavar="REF",
                        help="also build with commit REF, alternately, and print the ratios")
    parser.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.scene, args.child, args.deskew)
        return
    scene = ensure_scene(args.scene, max(args.sizes))
    base = baseline_tree(args.baseline) if args.baseline else None
    print(f"scene {scene}; {os.cpu_count()} cores, load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} before the runs "
          f"(a shared machine: other jobs slow the wall times)")
    if base is not None:
        print(f"A = this checkout ({REPO}), B = {args.baseline} ({base}); run A B A B ...")
    rows = []
    for count in args.sizes:
        runs_a, runs_b, ratios = [], [], []
        for k in range(args.repeats):
            runs_a.append(run_child(scene, count, args.threads, args.deskew))
            if base is None:
                continue
            runs_b.append(run_child(scene, count, args.threads, args.deskew, base))
            a, b = runs_a[-1], runs_b[-1]
            ratios.append(a["wall"] / b["wall"])
            print(f"  pair {k + 1}: A {a['wall']:.1f} s {a['peak_mb']:.0f} MB, B {b['wall']:.1f} s "
                  f"{b['peak_mb']:.0f} MB, A/B wall {ratios[-1]:.2f}, CPU "
                  f"{a['cpu'] / b['cpu']:.2f}, peak {a['peak_mb'] / b['peak_mb']:.2f}; load "
                  f"{os.getloadavg()[0]:.2f}", flush=True)
        print(describe("A " if base is not None else "", runs_a), flush=True)
        if base is not None:
            print(describe("B ", runs_b), flush=True)
            peak_a = np.median([r["peak_mb"] for r in runs_a])
            peak_b = np.median([r["peak_mb"] for r in runs_b])
            print(f"{count} scans, A/B pair by pair: wall {' '.join(f'{r:.2f}' for r in ratios)} "
                  f"(median {np.median(ratios):.2f}); median peak memory A {peak_a:.0f} MB, "
                  f"B {peak_b:.0f} MB ({peak_a / peak_b:.2f}x); map points A "
                  f"{runs_a[-1]['map_points'] / 1e6:.2f} M, B {runs_b[-1]['map_points'] / 1e6:.2f} M",
                  flush=True)
        rows.append((count, float(np.median([r["wall"] for r in runs_a])),
                     float(np.median([r["peak_mb"] for r in runs_a]))))
    print(f"load average after the runs {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if len(rows) > 1:
        (n0, w0, m0), (n1, w1, m1) = rows[0], rows[-1]
        print(f"growth {n0} -> {n1} scans ({n1 / n0:.1f}x): time {w1 / w0:.2f}x "
              f"({w0 / n0 * 1e3:.0f} -> {w1 / n1 * 1e3:.0f} ms per scan), peak memory "
              f"{m1 / m0:.2f}x ({m0:.0f} -> {m1:.0f} MB)")


if __name__ == "__main__":
    main()
