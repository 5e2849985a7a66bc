"""The calibrate action's feedback rate and cancel latency, seen by a client in another process.

The calibrator promises feedback at least once a second while a goal runs and an answer to a
cancel within about a second (docs/ros.md). Tests check that feedback and cancels arrive; how fast
they arrive depends on the machine and its load, so the figures are measured here:

- feedback: the gaps between consecutive feedback messages of a long goal (median, 95th percentile,
  max) over ``--seconds`` of its run;
- cancel: from the client's cancel request to the goal's result, ``--cancels`` times, half of them
  while the engine prepares the map (sent right after acceptance) and half mid-search.

    semcal scene --kind junction --seed 0 --size small --no-bag --out /tmp/junction0
    python benchmarks/bench_action_latency.py --scene /tmp/junction0
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True, help="a scene folder (semcal scene)")
    ap.add_argument("--seconds", type=float, default=20.0, help="feedback collected this long")
    ap.add_argument("--cancels", type=int, default=6, help="cancels measured (default 6)")
    ap.add_argument("--logs", type=Path, help="folder for the node's log")
    args = ap.parse_args()

    import rclpy
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.io.files import read_pose
    from semcal_ros.ros import qos
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal
    from semcal_tools.launch import NodeGraph
    from semcal_ros.ros.scene_messages import camera_messages

    entry = {"folder": ".", "frame_id": "camera_optical",
             "topics": {"labels": "/camera/labels", "image_raw": "/camera/image_raw",
                        "camera_info": "/camera/camera_info"}}
    logs = args.logs or Path(tempfile.mkdtemp(prefix="bench-action-"))
    print(f"load before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; scene {args.scene}",
          flush=True)
    with NodeGraph(logs) as graph:
        graph.start_node("calibrator", params={"map_file": str(args.scene / "map.ply")})
        ctx = graph.context()
        node = rclpy.create_node("bench_action_latency", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        msgs = camera_messages(args.scene, entry, 1.0)
        pubs = {t: node.create_publisher(CameraInfo if "info" in t else Image, t, qos.reliable(1))
                for t in msgs}
        node.create_timer(0.5, lambda: [pubs[t].publish(m) for t, m in msgs.items()])
        watcher = DiagnosticsWatcher(node)
        watcher.wait(executor, lambda: watcher.get("calibrator").get("message") == "ready", 120,
                     "the calibrator to be ready")
        client = CalibrateClient(node)
        client.wait_for_server(60)
        initial = read_pose(args.scene / "initial.yaml")

        goal = client.send(executor, make_goal(initial, verification_starts=30))
        end = time.monotonic() + args.seconds  # the goal (30 verification starts) runs longer
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        gaps = np.diff([t for t, _ in goal.feedback])
        client.cancel(executor, goal)
        client.wait(executor, goal, timeout=120)

        cancels: dict[str, list[float]] = {"preparing": [], "searching": []}
        for i in range(args.cancels):
            watcher.latest.pop("calibrator", None)  # a status sent from now on
            watcher.wait(executor, lambda: watcher.get("calibrator").get("state") == "idle", 120,
                         "the engine to be idle")
            when = "preparing" if i % 2 == 0 else "searching"
            outcome = client.send(executor, make_goal(initial))
            if not outcome.accepted:
                raise RuntimeError("goal not accepted")
            if when == "searching":
                watcher.wait(executor, lambda: bool(outcome.feedback)
                             and outcome.feedback[-1][1].evaluations > 0, 120, "the search")
            t0 = time.monotonic()
            client.cancel(executor, outcome)
            client.wait(executor, outcome, timeout=120)
            cancels[when].append(time.monotonic() - t0)
        executor.shutdown()
        node.destroy_node()

    print(f"load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if len(gaps):
        print(f"feedback: {len(gaps) + 1} messages in {args.seconds:.0f} s; gap median "
              f"{np.median(gaps):.2f} s, p95 {np.percentile(gaps, 95):.2f} s, max {gaps.max():.2f} s")
    for when, seconds in cancels.items():
        if seconds:
            print(f"cancel while {when}: {len(seconds)}x, median {np.median(seconds):.2f} s, "
                  f"max {max(seconds):.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
