"""Scene generation time (target: one full scene in <= 2 minutes on 2 cores) and map size.

Generates full-size scenes (200 scans, 128 lines, bag and scans written) REPEAT times per
layout into a temporary folder and prints the median seconds per stage, the map size and the
bytes written. The machine may be shared: run it a few times and compare medians.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_scene.py [--repeat 3]
        [--kinds junction arterial highway] [--variant ideal] [--size full]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    from semcal_tools.scenes import KINDS, SIZES, generate_scene

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--kinds", nargs="+", default=list(KINDS))
    parser.add_argument("--variant", default="ideal")
    parser.add_argument("--size", default="full", choices=sorted(SIZES))
    parser.add_argument("--no-bag", action="store_true")
    args = parser.parse_args()
    options = replace(SIZES[args.size], write_bag=not args.no_bag)

    print(f"{args.size} scenes, variant {args.variant}, {options.scans} scans, "
          f"bag {'off' if args.no_bag else 'on'}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f} at start")
    print("| kind | total s (median) | runs | layout | camera | lidar | map | CPU s | map points "
          "| scan points | MB written |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for kind in args.kinds:
        seconds, stages, cpu = [], [], []
        for i in range(args.repeat):
            with tempfile.TemporaryDirectory(prefix="bench-scene-") as tmp:
                out = Path(tmp) / "scene"
                c0 = time.process_time()
                res = generate_scene(out, kind, i, args.variant, options, progress=False)
                cpu.append(time.process_time() - c0)
                seconds.append(res.summary["seconds"]["total"])
                stages.append(res.summary["seconds"])
                size = folder_bytes(out) / 1e6
                counts = res.summary["counts"]
                shutil.rmtree(out)
        med = {k: statistics.median(s[k] for s in stages) for k in stages[0]}
        print(f"| {kind} | {statistics.median(seconds):.1f} | "
              f"{', '.join(f'{s:.0f}' for s in seconds)} | {med['layout']:.1f} | "
              f"{med['camera']:.1f} | {med['lidar']:.1f} | {med['map']:.1f} | "
              f"{statistics.median(cpu):.0f} | {counts['map_points']} | {counts['scan_points']} | "
              f"{size:.0f} |", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
