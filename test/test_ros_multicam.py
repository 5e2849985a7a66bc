"""One calibrator process serving two cameras of one junction (``semcal scene --cameras 2``) on
one map, over DDS: goals for both cameras queue on the one engine thread (the first held running
until the test cancels it), a second goal for a busy camera and a goal for an unknown camera are
answered with the reason, both results are accurate
and carry a verdict, and /tf_static's latest TFMessage holds both transforms."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402
from semcal_ros.ros.scene_messages import camera_messages  # noqa: E402

from ros_helpers import RosGraph, held_goal, spin_until  # noqa: E402
from test_ros_calibrator import (assert_empty_transform, assert_quality,  # noqa: E402
                                 assert_same_pose, offline_calibration)

pytestmark = pytest.mark.ros

#: Cheap (about 4 s a goal): each result is judged against the offline engine's, not its error.
ENGINE = {"engine.schedule.max_evaluations": [120, 40, 30],
          "engine.schedule.restarts": [0, 0, 0], "engine.verification.starts": 0,
          "engine.quality.evidence_evaluations": 15}
STAMP = 1700000002.5  # the label images' stamp


def test_two_cameras_on_one_map(tmp_path, scene_factory):
    from sensor_msgs.msg import CameraInfo, Image
    from tf2_msgs.msg import TFMessage

    from semcal_ros.io.files import read_pose
    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal

    scene = scene_factory("junction", 0, "ideal", cameras=2, scans=20, write_scans=False)
    cams = yaml.safe_load((scene / "cameras.yaml").read_text())["cameras"]
    a, b = (c["name"] for c in cams)
    graph = RosGraph(tmp_path / "logs")
    ctx = graph.context()
    node = rclpy.create_node("multicam_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        proc = graph.start_node("calibrator", params={
            "map_file": str(scene / "map.ply"), "cameras": [a, b], **ENGINE})
        watcher = DiagnosticsWatcher(node)
        msgs = {**camera_messages(scene, cams[0], STAMP), **camera_messages(scene, cams[1], STAMP)}
        pubs = {t: node.create_publisher(CameraInfo if "info" in t else Image, t,
                                         qos.reliable(1)) for t in msgs}
        timer = node.create_timer(0.3, lambda: [pubs[t].publish(m) for t, m in msgs.items()])
        spin_until(executor, lambda: all(watcher.get(f"calibrator/{n}").get("message") == "ready"
                                         for n in (a, b)), 60, "both cameras to be ready")
        node.destroy_timer(timer)
        assert watcher.get("calibrator")["cameras"] == f"{a}, {b}"
        tf_static: list[Any] = []
        node.create_subscription(TFMessage, "/tf_static", tf_static.append, qos.latched())
        overlays: list[Any] = []
        node.create_subscription(Image, "/calibration/overlay", overlays.append, qos.latched())
        client = CalibrateClient(node)
        client.wait_for_server(30)

        def goal(cam: dict, frame: str) -> Any:
            return make_goal(read_pose(scene / cam["folder"] / "initial.yaml"),
                             camera_frame_id=frame)

        # a by its frame id, b by its name: b waits for a on the one engine thread. a's first
        # goal runs until it is cancelled here, so b is queued behind it however fast the
        # machine is; a's real goal is sent once the engine has moved on to b.
        holder = client.send(executor, held_goal(read_pose(scene / cams[0]["folder"] /
                                                           "initial.yaml"),
                                                 camera_frame_id=f"{a}_optical"))
        assert holder.accepted
        holder_id = bytes(holder.goal_handle.goal_id.uuid).hex()[:8]
        spin_until(executor, lambda: watcher.get(f"calibrator/{a}").get("state", "")
                   .startswith(f"running {holder_id}"), 30, f"{a}'s goal to run")
        second = client.send(executor, goal(cams[1], b))
        assert second.accepted
        spin_until(executor, lambda: second.feedback, 30, "feedback of the queued goal")
        assert second.feedback[0][1].stage == "queued", second.feedback[0][1]

        busy = client.call(executor, goal(cams[0], f"{a}_optical"), timeout=30)
        assert busy.status == "aborted" and not busy.result.success
        assert busy.result.message.startswith(
            f"busy: goal {holder_id} for camera '{a}' has been running for "), busy.result.message
        assert busy.result.message.endswith("(one calibration per camera at a time)")
        queued = client.call(executor, goal(cams[1], f"{b}_optical"), timeout=30)
        assert queued.status == "aborted" and f"for camera '{b}' is queued" in \
            queued.result.message, queued.result.message
        for frame, expected in (("rear_optical", f"invalid goal: unknown camera 'rear_optical': "
                                 f"this calibrator serves '{a}' ({a}_optical), '{b}' "
                                 f"({b}_optical)"),
                                ("", "invalid goal: camera_frame_id is empty but this "
                                     f"calibrator serves cameras '{a}'")):
            out = client.call(executor, goal(cams[0], frame), timeout=30)
            assert out.status == "aborted" and out.result.message.startswith(expected), \
                out.result.message
            assert "\n" not in out.result.message
            assert_empty_transform(out.result)

        client.cancel(executor, holder)
        client.wait(executor, holder, timeout=60)
        assert holder.status == "canceled", (holder.status, holder.result.message)
        # a's job has ended once the engine thread took b's (one job at a time)
        spin_until(executor, lambda: second.feedback[-1][1].stage != "queued", 60,
                   f"{b}'s goal to leave the queue")
        first = client.send(executor, goal(cams[0], f"{a}_optical"))
        assert first.accepted

        results = {}
        for cam, outcome in ((cams[1], second), (cams[0], first)):
            client.wait(executor, outcome, timeout=120)
            assert outcome.status == "succeeded", outcome.result.message
            r = outcome.result
            assert (r.transform.header.frame_id, r.transform.child_frame_id) == \
                ("map", cam["frame_id"])
            truth = read_pose(scene / cam["folder"] / "ground_truth.yaml")
            start = read_pose(scene / cam["folder"] / "initial.yaml")
            pose = conv.pose_from_transform(r.transform)
            dt, dr = translation_error(pose, truth), rotation_error_deg(pose, truth)
            print(f"{cam['name']}: {dt * 100:.1f} cm, {dr:.3f} deg, verdict {r.verdict}")
            # each camera's answer is the engine's for its own label image, CameraInfo and start
            # on the shared map (how far a cheap schedule gets from ~1 m off differs between
            # CPUs; benchmarks/bench_multicam.py measures the full procedure's accuracy)
            expected = offline_calibration(scene, ENGINE, start, scene / cam["folder"])
            assert_same_pose(pose, expected.pose, f"{cam['name']}'s result")
            assert r.verdict == expected.quality.verdict, (r.verdict, r.verdict_reason)
            assert translation_error(pose, start) > 0.01
            assert_quality(r)
            results[cam["frame_id"]] = r.transform

        # /tf_static: one TFMessage (the latest, transient local) holding both cameras
        spin_until(executor, lambda: tf_static and len(tf_static[-1].transforms) == 2, 30,
                   "a /tf_static message with both transforms")
        held = {t.child_frame_id: t for t in tf_static[-1].transforms}
        assert set(held) == set(results)
        for frame, transform in results.items():
            assert held[frame].transform == transform.transform

        # the overlay of the last result (a's goal was sent after b's had started): that
        # camera's picture, the verdict's banner on top
        spin_until(executor, lambda: overlays and overlays[-1].header.frame_id == f"{a}_optical",
                   30, f"{a}'s overlay")
        picture = conv.image_to_rgb(overlays[-1])
        assert picture.shape == (msgs[cams[0]["topics"]["camera_info"]].height,
                                 msgs[cams[0]["topics"]["camera_info"]].width, 3)
        from semcal_ros.engine.overlay import VERDICT_COLOURS

        banner = np.median(picture[:6, :40].reshape(-1, 3), axis=0)  # left of the text
        nearest = min(VERDICT_COLOURS, key=lambda v: np.abs(banner - VERDICT_COLOURS[v]).sum())
        assert nearest == first.result.verdict, (banner, first.result.verdict)

        # per-camera diagnostics carry the verdict and its figures; the level follows it
        watcher.latest.clear()
        spin_until(executor, lambda: all(watcher.get(f"calibrator/{n}").get("state") == "idle"
                                         for n in (a, b)), 30, "fresh per-camera diagnostics")
        for n in (a, b):
            d = watcher.get(f"calibrator/{n}")
            assert d["verdict"] in ("good", "inconclusive", "failed") and d["agreement"], d
            assert d["last_result"].startswith(f"calibrated '{n}_optical'"), d
            level = {"good": "0", "inconclusive": "1", "failed": "2"}[d["verdict"]]
            assert d["level"] == level, d
        assert proc.running() and "Traceback" not in proc.log()
        assert proc.log().count("prepared in") == 1  # the map prepared once, for both cameras
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())
