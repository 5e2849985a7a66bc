"""RSS of one calibrator process over many consecutive goals (issue 10: it grew 386 -> 1702 MB).

Starts the calibrator node (map_file = the scene's map) in a ROS domain of its own, publishes the
scene's label image, camera image and CameraInfo until it is ready, then sends ``--goals`` good
goals one after the other and prints the process's RSS (``/proc/PID/status`` VmRSS, and VmHWM,
the peak) after each. A cheap engine schedule (``--evaluations``, no verification starts) keeps
100 goals within minutes: what is measured is what each goal leaves behind, not the engine.

    python benchmarks/bench_calibrator_memory.py --scene /tmp/scene --goals 100

Without ``--scene`` the small junction scene is generated first (~40 s).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of ``pid`` in MB."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            key, kb = line.split(":")
            values[key] = int(kb.split()[0]) / 1024.0
    return values["VmRSS"], values["VmHWM"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, help="scene folder (default: generate junction small)")
    ap.add_argument("--goals", type=int, default=100)
    ap.add_argument("--evaluations", type=int, nargs=3, default=[40, 20, 20],
                    help="engine.schedule.max_evaluations per stage (default 40 20 20)")
    ap.add_argument("--verification-starts", type=int, default=0)
    ap.add_argument("--logs", type=Path, help="folder for the node's log")
    args = ap.parse_args()

    import rclpy
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose, read_rgb_image
    from semcal_ros.ros import conversions as conv
    from semcal_ros.ros import qos
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal
    from semcal_tools.launch import NodeGraph

    scene = args.scene
    if scene is None:
        from semcal_tools.scenes import SIZES, generate_scene

        scene = Path(tempfile.mkdtemp(prefix="bench-cal-mem-"))
        t = time.perf_counter()
        generate_scene(scene, "junction", 0, "ideal", SIZES["small"], progress=False)
        print(f"scene generated in {time.perf_counter() - t:.0f} s: {scene}", flush=True)
    logs = args.logs or Path(tempfile.mkdtemp(prefix="bench-cal-mem-logs-"))
    camera = read_camera_info(scene / "camera_info.yaml")
    header = conv.make_header(camera.frame_id, 1.0)
    msgs = {"/camera/labels": conv.numpy_to_image(read_label_image(scene / "labels.png"),
                                                  "mono8", header),
            "/camera/image_raw": conv.numpy_to_image(read_rgb_image(scene / "image.png"),
                                                     "rgb8", header),
            "/camera/camera_info": conv.model_to_camera_info(camera, header)}
    initial = read_pose(scene / "initial.yaml")

    with NodeGraph(logs) as graph:
        proc = graph.start_node("calibrator", params={
            "map_file": str(scene / "map.ply"),
            "engine.schedule.max_evaluations": list(args.evaluations),
            "engine.schedule.restarts": [0, 0, 0],
            "engine.verification.starts": args.verification_starts})
        ctx = graph.context()
        node = rclpy.create_node("bench_calibrator_memory", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        pubs = {t: node.create_publisher(CameraInfo if "info" in t else Image, t,
                                         qos.reliable(1)) for t in msgs}
        watcher = DiagnosticsWatcher(node)
        timer = node.create_timer(0.3, lambda: [pubs[t].publish(m) for t, m in msgs.items()])
        watcher.wait(executor, lambda: watcher.get("calibrator").get("message") == "ready", 120,
                     "the calibrator to be ready")
        node.destroy_timer(timer)
        client = CalibrateClient(node)
        client.wait_for_server(30)
        pid = proc.proc.pid
        idle = rss_mb(pid)
        print(f"calibrator pid {pid}: idle RSS {idle[0]:.1f} MB (peak {idle[1]:.1f} MB), "
              f"{args.goals} goals, max_evaluations {args.evaluations}, "
              f"{args.verification_starts} verification starts", flush=True)
        print("goal  status     seconds  RSS_MB  peak_MB", flush=True)
        t_all = time.perf_counter()
        rows = []
        for i in range(1, args.goals + 1):
            t = time.perf_counter()
            out = client.call(executor, make_goal(initial), timeout=600)
            if out.status != "succeeded":
                print(f"goal {i}: {out.status}: {out.result.message}", file=sys.stderr)
                return 1
            rss, peak = rss_mb(pid)
            rows.append(rss)
            print(f"{i:4d}  {out.status:9s}  {time.perf_counter() - t:7.2f}  {rss:6.1f}  "
                  f"{peak:7.1f}", flush=True)
        executor.shutdown()
        node.destroy_node()
    n = len(rows)
    if n >= 5:
        ref = rows[4]
        print(f"after goal 5: {ref:.1f} MB; after goal {n}: {rows[-1]:.1f} MB "
              f"({(rows[-1] - ref) / ref * 100:+.1f} %); min {min(rows):.1f}, "
              f"max {max(rows):.1f} MB; {time.perf_counter() - t_all:.0f} s for {n} goals")
    return 0


if __name__ == "__main__":
    sys.exit(main())
