"""Resident memory of the map_builder node over a looped bag replay (issue 6 target: flat once
the map is full).

Starts map_builder in a ROS domain of its own, replays the demo scene's bag in a loop with
bag_player for ``--minutes``, and samples the node's VmRSS (from /proc) and its /diagnostics every
``--every`` seconds. Two modes:

- ``full``: ``mapping.max_scans`` = the bag's scan count and no reset on the loop's time jump: the
  map fills in the first pass, every later scan is counted and ignored (the steady state of a
  vehicle that keeps driving after its map is complete).
- ``rebuild``: the map is reset at every loop (time jumps back) and rebuilt from the scans: the
  builder's own allocations are exercised again and again.

Prints the samples and a summary: RSS after the first pass, at the end, and the slope of a line
fitted to the second half (MB per minute). Example:

    .venv/bin/python benchmarks/bench_map_builder_memory.py --minutes 10 --mode full
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for process {pid}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--every", type=float, default=10.0, help="seconds between samples")
    ap.add_argument("--mode", choices=("full", "rebuild"), default="full")
    ap.add_argument("--out", help="folder for the scene and logs (default: temporary)")
    ap.add_argument("--icp", action="store_true", help="map builder with ICP (slower)")
    args = ap.parse_args()

    import rclpy

    from semcal_ros.ros.client import DiagnosticsWatcher
    from semcal_tools.launch import NodeGraph
    from semcal_tools.live_demo import ODOM_TOPIC, SCAN_TOPIC, ensure_scene, scan_count
    from semcal_ros.ros.runtime import config_file

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="semcal-bench-mem-"))
    scene = ensure_scene(out, 0)
    scans = scan_count(scene / "bag")
    params = {"mapping.icp": args.icp, "publish_period": 2.0}
    if args.mode == "full":
        params.update({"mapping.max_scans": scans, "reset_on_time_jump": False})
    with NodeGraph(out / f"logs-{args.mode}") as graph:
        builder = graph.start_node("map_builder", params_file=config_file("map_builder.yaml"),
                                   params=params, remap={"scan": SCAN_TOPIC, "odom": ODOM_TOPIC})
        builder.wait_for_log("ready", 60)
        ctx = graph.context()
        node = rclpy.create_node("bench_memory", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        watcher = DiagnosticsWatcher(node)
        graph.start_node("bag_player", params={"bag": str(scene / "bag"), "loop": True,
                                               "topics": [SCAN_TOPIC, ODOM_TOPIC],
                                               "wait_for_subscribers": 15.0})
        print(f"mode {args.mode}: map_builder pid {builder.proc.pid}, bag of {scans} scans "
              f"looped for {args.minutes:g} min (ICP {'on' if args.icp else 'off'})")
        print(f"{'t (s)':>7} {'RSS (MB)':>9} {'accepted':>9} {'ignored':>8} {'dropped':>8} "
              f"{'resets':>7} {'map pts':>9}")
        t0 = time.monotonic()
        samples = []
        next_sample = t0
        while time.monotonic() - t0 < args.minutes * 60:
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() < next_sample:
                continue
            next_sample += args.every
            if not builder.running():
                raise RuntimeError(f"map_builder exited:\n{builder.log()}")
            d = watcher.get("map_builder")
            t, rss = time.monotonic() - t0, rss_mb(builder.proc.pid)
            samples.append((t, rss, int(d.get("scans_accepted", 0) or 0)))
            print(f"{t:7.0f} {rss:9.1f} {d.get('scans_accepted', '-'):>9} "
                  f"{d.get('ignored_map_full', '-'):>8} {d.get('dropped_queue_full', '-'):>8} "
                  f"{d.get('resets', '-'):>7} {d.get('map_points', '-'):>9}", flush=True)
        arr = np.array(samples)
        first_full = np.argmax(arr[:, 2] >= scans) if np.any(arr[:, 2] >= scans) else 0
        half = arr[len(arr) // 2:]
        slope = np.polyfit(half[:, 0] / 60.0, half[:, 1], 1)[0] if len(half) > 2 else float("nan")
        print(f"\nRSS when the first {scans} scans were in: {arr[first_full, 1]:.1f} MB "
              f"(t = {arr[first_full, 0]:.0f} s); min/max after that "
              f"{arr[first_full:, 1].min():.1f}/{arr[first_full:, 1].max():.1f} MB; "
              f"end {arr[-1, 1]:.1f} MB")
        print(f"slope over the second half: {slope:+.2f} MB/min")
        # In rebuild mode the RSS swings with the map being rebuilt; its lower envelope (the
        # minimum per window) is what would rise with a leak.
        window = 120.0
        lows = [f"{arr[(arr[:, 0] >= w) & (arr[:, 0] < w + window), 1].min():.1f}"
                for w in np.arange(0.0, arr[-1, 0], window)
                if np.any((arr[:, 0] >= w) & (arr[:, 0] < w + window))]
        print(f"minimum RSS per {window:.0f} s window (MB): {', '.join(lows)}")
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
