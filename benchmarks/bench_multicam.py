"""Multi-camera calibrator: memory with 4 cameras vs 1 on one map, and each camera's accuracy in the
4-camera node vs calibrated alone (issue 13: RSS(4) <= RSS(1) + 150 MB; each result as accurate).

Uses a scene of ``semcal scene --cameras N`` (the small size makes a ~2.4 M-point map). Runs

1. a calibrator serving only the first camera: its goal, RSS (VmRSS) when ready and after the goal,
   and the peak (VmHWM);
2. a calibrator serving every camera: one goal per camera sent at once (they queue on the one engine
   thread), the same RSS figures, and each result's error against the camera's ground truth;
3. each camera alone, in this process, as ``semcal calibrate`` does it
   (:func:`semcal_ros.engine.search.calibrate`: the map cropped around the initial pose and prepared for
   that one calibration), with the same engine parameters and seed.

    semcal scene --size small --cameras 4 --no-bag --out /tmp/mc4
    python benchmarks/bench_multicam.py --scene /tmp/mc4
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_calibrator_memory import rss_mb  # noqa: E402

from semcal_ros.ros.scene_messages import camera_messages  # noqa: E402


def run_node(scene: Path, cams: list[dict], engine: dict, logs: Path) -> dict:
    """Start a calibrator serving ``cams``, send one goal per camera at once, wait for all."""
    import rclpy
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.io.files import read_pose
    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.ros import conversions as conv
    from semcal_ros.ros import qos
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal
    from semcal_tools.launch import NodeGraph

    names = [c["name"] for c in cams]
    out: dict = {"errors": {}}
    with NodeGraph(logs) as graph:
        t0 = time.perf_counter()
        proc = graph.start_node("calibrator", params={
            "map_file": str(scene / "map.ply"), "cameras": names, **engine})
        ctx = graph.context()
        node = rclpy.create_node("bench_multicam", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        msgs = {}
        for cam in cams:
            msgs.update(camera_messages(scene, cam, 1.0))
        pubs = {t: node.create_publisher(CameraInfo if "info" in t else Image, t,
                                         qos.reliable(1)) for t in msgs}
        watcher = DiagnosticsWatcher(node)
        timer = node.create_timer(0.3, lambda: [pubs[t].publish(m) for t, m in msgs.items()])
        watcher.wait(executor, lambda: all(watcher.get(f"calibrator/{n}").get("message")
                                           == "ready" for n in names), 180,
                     "every camera to be ready")
        node.destroy_timer(timer)
        out["ready_s"] = time.perf_counter() - t0
        client = CalibrateClient(node)
        client.wait_for_server(30)
        pid = proc.proc.pid
        out["ready_rss"] = rss_mb(pid)
        t = time.perf_counter()
        sent = [(cam, client.send(executor, make_goal(
            read_pose(scene / cam["folder"] / "initial.yaml"), camera_frame_id=cam["frame_id"])))
            for cam in cams]
        for cam, outcome in sent:
            client.wait(executor, outcome, timeout=1800)
            if outcome.status != "succeeded":
                raise RuntimeError(f"{cam['name']}: {outcome.status}: {outcome.result.message}")
            truth = read_pose(scene / cam["folder"] / "ground_truth.yaml")
            pose = conv.pose_from_transform(outcome.result.transform)
            out["errors"][cam["name"]] = (translation_error(pose, truth),
                                          rotation_error_deg(pose, truth),
                                          outcome.result.verdict, outcome.result.seconds)
        out["goals_s"] = time.perf_counter() - t
        out["after_rss"] = rss_mb(pid)
        executor.shutdown()
        node.destroy_node()
    return out


def alone(scene: Path, cams: list[dict], engine: dict) -> dict:
    """Each camera calibrated by itself as ``semcal calibrate`` does (map cropped and prepared
    per calibration)."""
    from semcal_ros.engine.config import apply_flat
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply
    from semcal_ros.engine.search import calibrate
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import rotation_error_deg, translation_error

    params = apply_flat(CalibrationParams(), {k[len("engine."):]: v for k, v in engine.items()})
    cloud = read_ply(scene / "map.ply")
    out = {}
    for cam in cams:
        folder = scene / cam["folder"]
        result = calibrate(cloud, read_label_image(folder / "labels.png"),
                           read_camera_info(folder / "camera_info.yaml"),
                           read_pose(folder / "initial.yaml"), params, seed=0)
        truth = read_pose(folder / "ground_truth.yaml")
        out[cam["name"]] = (translation_error(result.pose, truth),
                            rotation_error_deg(result.pose, truth), result.quality.verdict,
                            result.seconds)
    return out


def main() -> int:
    import yaml

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True,
                    help="folder of semcal scene --cameras N (N >= 2)")
    ap.add_argument("--verification-starts", type=int, default=2,
                    help="engine.verification.starts (default 2; the node default is 6)")
    ap.add_argument("--logs", type=Path, help="folder for the nodes' logs")
    args = ap.parse_args()
    cams = yaml.safe_load((args.scene / "cameras.yaml").read_text())["cameras"]
    engine = {"engine.verification.starts": args.verification_starts}
    logs = args.logs or Path(tempfile.mkdtemp(prefix="bench-multicam-"))
    print(f"load before: {os.getloadavg()[0]:.2f}; scene {args.scene}, cameras "
          f"{', '.join(c['name'] for c in cams)}, verification starts "
          f"{args.verification_starts}", flush=True)
    one = run_node(args.scene, cams[:1], engine, logs / "one")
    every = run_node(args.scene, cams, engine, logs / "all")
    by_itself = alone(args.scene, cams, engine)
    print(f"\n{'node':10s} {'ready s':>8s} {'RSS ready':>10s} {'RSS after':>10s} {'peak':>8s} "
          f"{'goals s':>8s}")
    for label, r in (("1 camera", one), (f"{len(cams)} cameras", every)):
        print(f"{label:10s} {r['ready_s']:8.1f} {r['ready_rss'][0]:10.1f} "
              f"{r['after_rss'][0]:10.1f} {r['after_rss'][1]:8.1f} {r['goals_s']:8.1f}")
    extra = every["after_rss"][1] - one["after_rss"][1]
    print(f"peak RSS, {len(cams)} cameras - 1 camera: {extra:+.1f} MB (target <= +150 MB: "
          f"{'met' if extra <= 150 else 'MISSED'})")
    print(f"\n{'camera':10s} {'node cm':>8s} {'deg':>6s} {'verdict':>13s} {'alone cm':>9s} "
          f"{'deg':>6s} {'verdict':>13s}")
    for cam in cams:
        n, a = every["errors"][cam["name"]], by_itself[cam["name"]]
        print(f"{cam['name']:10s} {n[0] * 100:8.2f} {n[1]:6.3f} {n[2]:>13s} {a[0] * 100:9.2f} "
              f"{a[1]:6.3f} {a[2]:>13s}")
    first = cams[0]["name"]
    print(f"{first} in the 1-camera node: {one['errors'][first][0] * 100:.2f} cm, "
          f"{one['errors'][first][1]:.3f} deg")
    print(f"load after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
