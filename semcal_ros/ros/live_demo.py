"""``semcal demo``: the live ROS 2 pipeline on the demo scene, start to finish.

Generates the small junction scene (with its bag), starts ``map_builder`` and ``calibrator`` as
processes in a ROS domain of their own (localhost only), replays the bag with ``bag_player``,
waits until the calibrator holds the map of every scan, calls the ``calibrate`` action with the
scene's perturbed ``initial.yaml`` and prints the transform, its error against
``ground_truth.yaml``, the timings and where the overlay picture is.

The scene's poses are exact (a simulation), so the map builder runs without ICP here: ICP would
only cost time (``mapping.icp`` stays on in ``config/map_builder.yaml`` for real drives).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from semcal_ros.ros.runtime import config_file

SCAN_TOPIC, ODOM_TOPIC = "/lidar/points", "/lidar/odom"


@dataclass
class DemoOptions:
    out: Path
    seed: int = 0
    verification_starts: int = -1  # -1: the calibrator's configured number (the full default)
    timeout: float = 600.0  # s for the whole live part


def ensure_scene(out: Path, seed: int) -> Path:
    """The demo scene with its bag (generated once per output folder)."""
    from semcal_ros.cli import main as semcal

    scene = out / "scene"
    if (scene / "bag" / "metadata.yaml").is_file() and (scene / "initial.yaml").is_file():
        print(f"using the demo scene in {scene}")
        return scene
    print(f"generating the demo scene (junction, seed {seed}, 50 scans, bag) in {scene} ...")
    code = semcal(["scene", "--kind", "junction", "--seed", str(seed), "--size", "small",
                   "--out", str(scene), "--force"])
    if code:
        raise RuntimeError("scene generation failed")
    return scene


def scan_count(bag: Path) -> int:
    from semcal_ros.ros.replay import open_bag

    reader = open_bag(bag)
    try:
        return sum(c.msgcount for c in reader.connections if c.topic == SCAN_TOPIC)
    finally:
        reader.close()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a running process (the load-independent cost of its work)."""
    import os

    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_live(opts: DemoOptions) -> int:
    import rclpy
    from tqdm import tqdm

    from semcal_ros.io.files import read_pose
    from semcal_ros.pose import rotation_error_deg, translation_error
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal
    from semcal_ros.ros.conversions import pose_from_transform
    from semcal_ros.ros.launch import NodeGraph

    out = opts.out
    scene = ensure_scene(out, opts.seed)
    scans = scan_count(scene / "bag")
    graph = NodeGraph(out / "logs")
    deadline = time.monotonic() + opts.timeout
    try:
        print(f"starting map_builder and calibrator (ROS_DOMAIN_ID {graph.domain}, localhost "
              f"only; logs in {graph.log_dir})")
        builder = graph.start_node(
            "map_builder", params_file=config_file("map_builder.yaml"),
            params={"mapping.icp": False, "publish_period": 1.0, "queue_size": 100,
                    "save_path": str(out / "map.ply")},
            remap={"scan": SCAN_TOPIC, "odom": ODOM_TOPIC})
        calibrator = graph.start_node(
            "calibrator", params_file=config_file("calibrator.yaml"),
            params={"overlay_file": str(out / "overlay.png")})
        ctx = graph.context()
        node = rclpy.create_node("semcal_demo", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        watcher = DiagnosticsWatcher(node)
        client = CalibrateClient(node)
        builder.wait_for_log("ready", 60)
        calibrator.wait_for_log("ready", 60)
        client.wait_for_server(30)

        cpu0 = {p.name: cpu_seconds(p.proc.pid) for p in (builder, calibrator)}
        t_bag = time.monotonic()
        graph.start_node("bag_player", params={"bag": str(scene / "bag"),
                                               "wait_for_subscribers": 15.0})
        with tqdm(total=scans, desc="map (scans)", unit="scan") as bar:
            def mapped() -> bool:
                done = int(watcher.get("map_builder").get("scans_accepted", "0") or 0)
                bar.update(max(done - bar.n, 0))
                return watcher.map_ready(scans)

            watcher.wait(executor, mapped, deadline - time.monotonic(),
                         f"the calibrator to hold the map of all {scans} scans")
        t_map = time.monotonic()
        points = watcher.get("calibrator").get("map_points")
        print(f"map of {scans} scans ({points} points) held by the calibrator after "
              f"{t_map - t_bag:.1f} s")

        initial = read_pose(scene / "initial.yaml")
        truth = read_pose(scene / "ground_truth.yaml")
        print(f"calling 'calibrate' from initial.yaml: {translation_error(initial, truth):.2f} m "
              f"and {rotation_error_deg(initial, truth):.2f} deg off the ground truth")
        goal = make_goal(initial, verification_starts=opts.verification_starts)
        with tqdm(desc="calibrate", unit=" feedback", bar_format="{desc}: {elapsed} {postfix}"
                  ) as bar:
            def on_feedback(fb) -> None:
                bar.set_postfix_str(f"{fb.stage}, {fb.evaluations} evaluations, best loss "
                                    f"{fb.best_loss:.5f}")

            outcome = client.call(executor, goal, timeout=deadline - time.monotonic(),
                                  on_feedback=on_feedback)
        t_result = time.monotonic()
        cpu = {p.name: cpu_seconds(p.proc.pid) - cpu0[p.name] for p in (builder, calibrator)}
        if not outcome.accepted or outcome.status != "succeeded":
            print(f"calibration {outcome.status or 'rejected'}: "
                  f"{outcome.result.message if outcome.result else ''}")
            return 1
        result = outcome.result
        pose = pose_from_transform(result.transform)
        tr, rot = result.transform.transform.translation, result.transform.transform.rotation
        print(f"\n{result.message}")
        print(f"transform {result.transform.header.frame_id} -> {result.transform.child_frame_id}:"
              f"\n  translation [{tr.x:.4f}, {tr.y:.4f}, {tr.z:.4f}] m"
              f"\n  rotation    [{rot.x:.5f}, {rot.y:.5f}, {rot.z:.5f}, {rot.w:.5f}] (x y z w)"
              f"\n  body rpy    [{', '.join(f'{v:.3f}' for v in pose.body_rpy_deg())}] deg")
        print(f"error against ground_truth.yaml: {translation_error(pose, truth) * 100:.2f} cm, "
              f"{rotation_error_deg(pose, truth):.3f} deg")
        print(f"timing: bag start -> map held {t_map - t_bag:.1f} s, action {t_result - t_map:.1f}"
              f" s, bag start -> result {t_result - t_bag:.1f} s "
              f"({len(outcome.feedback)} feedback messages)")
        print(f"CPU time since the bag started: map_builder {cpu['map_builder']:.1f} s, "
              f"calibrator {cpu['calibrator']:.1f} s (wall time depends on what else runs)")
        print(f"overlay picture: {out / 'overlay.png'}")
        print(f"also published: /calibration/transform (latched), /tf_static, "
              f"/calibration/overlay")
        return 0
    except (TimeoutError, RuntimeError) as exc:
        print(f"demo failed: {exc}")
        print(f"node logs: {graph.log_dir}")
        return 1
    finally:
        graph.close()
