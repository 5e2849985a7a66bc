"""One calibrator process, many goals: every result of every goal sequence reaches the caller.

The calibrator runs as a real process (DDS on localhost) on the demo scene's map with a cheap
engine schedule (about 3 s a goal), so sequences of goals fit in the suite. The process is shared
by the tests of this module (module-scoped fixture): what one goal leaves behind is exactly what
these tests are about.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, RosProcess, spin_until  # noqa: E402

pytestmark = pytest.mark.ros

#: An engine schedule that converges roughly in ~80 evaluations (about 3 s on the demo map):
#: these tests are about the node, not the optimum.
CHEAP_ENGINE = {"schedule.max_evaluations": [40, 20, 20], "schedule.final_restarts": 0,
                "verification.starts": 0}


@dataclass
class Calibrator:
    """The calibrator process and a client node in its domain."""

    graph: RosGraph
    proc: RosProcess
    node: Any
    executor: Any
    client: Any
    watcher: Any
    scene: Path
    camera_msgs: dict[str, Any]

    def diag(self) -> dict[str, str]:
        return self.watcher.get("calibrator")

    def call(self, goal: Any, timeout: float = 120.0) -> Any:
        return self.client.call(self.executor, goal, timeout=timeout)

    def good_goal(self, **options: Any) -> Any:
        from semcal_ros.io.files import read_pose
        from semcal_ros.ros.client import make_goal

        return make_goal(read_pose(self.scene / "initial.yaml"), **options)


def camera_messages(scene: Path) -> dict[str, Any]:
    from semcal_ros.io.files import read_camera_info, read_label_image, read_rgb_image

    camera = read_camera_info(scene / "camera_info.yaml")
    header = conv.make_header(camera.frame_id, 1700000002.5)
    return {"/camera/labels": conv.numpy_to_image(read_label_image(scene / "labels.png"),
                                                  "mono8", header),
            "/camera/image_raw": conv.numpy_to_image(read_rgb_image(scene / "image.png"),
                                                     "rgb8", header),
            "/camera/camera_info": conv.model_to_camera_info(camera, header)}


@pytest.fixture(scope="module")
def calibrator(tmp_path_factory, demo_scene):
    """A calibrator holding the demo map (map_file), a label image and CameraInfo; the camera
    messages are published until it says 'ready', then no more (it must keep what it holds)."""
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher

    graph = RosGraph(tmp_path_factory.mktemp("calibrator"))
    ctx = graph.context()
    node = rclpy.create_node("goal_sequences", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        proc = graph.start_node("calibrator", params={"map_file": str(demo_scene / "map.ply"),
                                                      **CHEAP_ENGINE})
        watcher = DiagnosticsWatcher(node)
        msgs = camera_messages(demo_scene)
        pubs = {topic: node.create_publisher(CameraInfo if "info" in topic else Image, topic,
                                             qos.reliable(1)) for topic in msgs}
        timer = node.create_timer(0.3, lambda: [pubs[t].publish(m) for t, m in msgs.items()])
        spin_until(executor, lambda: watcher.get("calibrator").get("message") == "ready", 60,
                   "the calibrator to hold a map, a label image and CameraInfo")
        node.destroy_timer(timer)
        client = CalibrateClient(node)
        client.wait_for_server(20)
        yield Calibrator(graph, proc, node, executor, client, watcher, demo_scene, msgs)
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())  # shown by pytest only when a test failed


# --- what each kind of result must carry -------------------------------------------------------
def assert_empty_transform(result: Any) -> None:
    from geometry_msgs.msg import TransformStamped

    assert result.transform == TransformStamped(), result.transform  # no pose on failure


def assert_aborted(out: Any, *texts: str) -> None:
    assert out.accepted and out.status == "aborted", (out.status, out.result)
    r = out.result
    assert r.success is False
    assert r.message, "an aborted goal must say why"
    for text in texts:
        assert text in r.message, r.message
    assert_empty_transform(r)
    assert (r.loss, r.spread_translation_m, r.spread_rotation_deg) == (0.0, 0.0, 0.0)
    assert r.evaluations == 0


def assert_cancelled(out: Any) -> None:
    assert out.status == "canceled", (out.status, out.result)
    r = out.result
    assert r.success is False
    assert r.message.startswith("cancelled after "), r.message
    assert_empty_transform(r)
    assert r.loss == 0.0 and r.evaluations >= 0 and r.seconds >= 0.0


def assert_succeeded(out: Any, scene: Path) -> None:
    from semcal_ros.io.files import read_pose
    from semcal_ros.pose import translation_error

    assert out.accepted and out.status == "succeeded", (out.status, out.result)
    r = out.result
    assert r.success is True
    assert r.message.startswith("calibrated 'camera_optical': t = ["), r.message
    assert f"loss {r.loss:.5f}" in r.message and "1/1 runs agree" in r.message
    assert (r.transform.header.frame_id, r.transform.child_frame_id) == ("map", "camera_optical")
    pose = conv.pose_from_transform(r.transform)
    truth = read_pose(scene / "ground_truth.yaml")
    start = read_pose(scene / "initial.yaml")
    # the cheap schedule gets most of the way from 1.12 m off; the node must not lose that
    assert translation_error(pose, truth) < 0.5 * translation_error(start, truth)
    assert abs(np.linalg.norm(pose.quaternion) - 1.0) < 1e-6
    assert 0.0 < r.loss < 1.0 and math.isfinite(r.loss)
    assert 0 < r.evaluations <= sum(CHEAP_ENGINE["schedule.max_evaluations"]) + 10
    assert r.seconds > 0.0
    assert (r.spread_translation_m, r.spread_rotation_deg) == (0.0, 0.0)  # one run


def test_goal_sequences_on_one_calibrator_lose_no_result(calibrator):
    """abort -> succeed -> abort -> cancel -> succeed -> abort on one process: each result whole
    (rclpy once turned every result after the first of another severity into an empty one)."""
    c = calibrator
    frame_problem = c.good_goal(map_frame="odom")
    bad_quaternion = c.good_goal()
    bad_quaternion.initial_pose.pose.orientation.w = 2.0

    assert_aborted(c.call(frame_problem), "invalid goal",
                   "initial_pose is in frame 'odom' but the map is in 'map'")
    assert_succeeded(c.call(c.good_goal()), c.scene)
    assert_aborted(c.call(bad_quaternion), "invalid goal", "not a unit quaternion")

    running = c.client.send(c.executor, c.good_goal())
    assert running.accepted
    c.client.cancel(c.executor, running)
    assert_cancelled(c.client.wait(c.executor, running, timeout=20))
    spin_until(c.executor, lambda: c.diag().get("state") == "idle", 30, "the engine to stop")

    assert_succeeded(c.call(c.good_goal()), c.scene)
    assert_aborted(c.call(frame_problem), "initial_pose is in frame 'odom'")
    assert c.proc.running()
    assert "Error raised in execute callback" not in c.proc.log()
