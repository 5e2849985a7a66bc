"""Does the live ``map_builder`` keep up with a 10 Hz lidar of ~130k points per scan?

A synthetic junction drive (88 lidar lines, ~129k labelled points per scan, ``--scans`` at
10 Hz) is generated once with its bag, then replayed in real time by ``bag_player`` into a
``map_builder`` started with ``config/map_builder.yaml`` (ICP on, de-skew as configured), each
in a ROS domain of its own. While the bag plays, the node's /diagnostics are sampled: its own
amortised seconds of work per scan (``seconds_per_scan``, over the last ``budget_window``
scans) and whether it warned that it falls behind. Afterwards the script prints the scans
played, accepted and dropped, the node's CPU seconds per scan over the replay (from /proc:
everything the process did, amortised), and how long after the bag's last scan the map held
every scan (the lag). Kept up = every scan accepted, none dropped, per-scan work <= 0.1 s.

    .venv/bin/python benchmarks/bench_map_builder_live.py [--scans 100] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

LINES = 88


def ensure_scene(folder: Path, scans: int) -> Path:
    """The cached scene with its bag (a child process: the generator's memory stays there)."""
    if (folder / "bag" / "metadata.yaml").is_file():
        return folder
    print(f"generating {scans} scans with their bag into {folder} (once) ...", flush=True)
    code = ("import sys; from pathlib import Path; "
            "from semcal_tools.scenes.generate import SceneOptions, generate_scene; "
            "generate_scene(Path(sys.argv[1]), 'junction', 0, 'ideal', SceneOptions("
            "scans=int(sys.argv[2]), lines=int(sys.argv[3]), write_bag=True), force=True, "
            "progress=False)")
    subprocess.run([sys.executable, "-c", code, str(folder), str(scans), str(LINES)], check=True)
    return folder


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=100)
    ap.add_argument("--out", type=Path,
                    default=Path(os.environ.get("TMPDIR", "/tmp")) / "semcal-bench-live")
    args = ap.parse_args()

    import rclpy

    from semcal_ros.ros.client import DiagnosticsWatcher
    from semcal_ros.ros.runtime import config_file
    from semcal_tools.launch import NodeGraph
    from semcal_tools.live_demo import ODOM_TOPIC, SCAN_TOPIC, scan_count

    scene = ensure_scene(args.out / f"scene-{LINES}l-{args.scans}", args.scans)
    scans = scan_count(scene / "bag")
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"bag {scene / 'bag'}: {scans} scans at 10 Hz; {os.cpu_count()} cores, load {load}")
    with NodeGraph(args.out / "logs") as graph:
        builder = graph.start_node("map_builder", params_file=config_file("map_builder.yaml"),
                                   remap={"scan": SCAN_TOPIC, "odom": ODOM_TOPIC})
        builder.wait_for_log("ready", 60)
        ctx = graph.context()
        node = rclpy.create_node("bench_live", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        watcher = DiagnosticsWatcher(node)
        cpu0 = cpu_seconds(builder.proc.pid)
        player = graph.start_node("bag_player", params={
            "bag": str(scene / "bag"), "topics": [SCAN_TOPIC, ODOM_TOPIC],
            "wait_for_subscribers": 15.0})
        samples, warned, t0 = [], [], time.monotonic()
        while player.running() and time.monotonic() - t0 < scans * 0.1 + 120:
            executor.spin_once(timeout_sec=0.1)
            d = watcher.get("map_builder")
            if d.get("seconds_per_scan") not in (None, "0.0"):
                samples.append(float(d["seconds_per_scan"]))
            if "falling behind" in d.get("message", ""):
                warned.append(d["message"])
        bag_end = time.monotonic()
        deadline = bag_end + 120
        done = None
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
            d = watcher.get("map_builder")
            handled = (int(d.get("scans_accepted", 0) or 0) + int(d.get("dropped_queue_full", 0)
                                                                  or 0))
            if handled >= scans and int(d.get("scans_queued", 1) or 0) == 0:
                done = time.monotonic()
                break
        cpu = cpu_seconds(builder.proc.pid) - cpu0
        d = watcher.get("map_builder")
        accepted = int(d.get("scans_accepted", 0) or 0)
        dropped = int(d.get("dropped_queue_full", 0) or 0)
        print(f"played {scans} scans in {bag_end - t0:.1f} s; accepted {accepted}, dropped "
              f"(queue full) {dropped}, map {d.get('map_points')} points")
        if samples:
            arr = np.array(samples)
            print(f"node's work per scan (amortised over its window): end "
                  f"{arr[-1] * 1e3:.0f} ms, median {np.median(arr) * 1e3:.0f} ms, max "
                  f"{arr.max() * 1e3:.0f} ms (budget {float(d.get('scan_budget', 0)) * 1e3:.0f} "
                  f"ms)")
        print(f"node CPU over the replay: {cpu:.1f} s = {cpu / max(accepted, 1) * 1e3:.0f} ms "
              f"per accepted scan (all threads, publications included)")
        print(f"lag: every scan in {'%.1f s' % (done - bag_end) if done else 'NOT within 120 s'} "
              f"after the bag's end; 'falling behind' warnings: {len(warned)}")
        print(f"load after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
        kept_up = accepted == scans and dropped == 0 and samples and max(samples) <= 0.1
        print(f"kept up with 10 Hz (<= 100 ms per scan, nothing dropped): "
              f"{'yes' if kept_up else 'NO'}")
        node.destroy_node()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
