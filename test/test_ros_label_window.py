"""A static camera's window of label images (``label_window``): the calibrator process keeps the
last N label images it received and calibrates against their per-pixel fusion (DDS on
localhost, the demo scene's map, a cheap engine schedule)."""

from __future__ import annotations

import re

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, publish_until, spin_until  # noqa: E402

pytestmark = pytest.mark.ros

CHEAP_ENGINE = {"engine.schedule.max_evaluations": [40, 20, 20],
                "engine.schedule.restarts": [0, 0, 0], "engine.verification.starts": 0,
                "engine.quality.evidence_evaluations": 15}


def passing_cars(labels: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` copies of ``labels``, each with a car (trainId 13) in another place of the road
    half: every pixel shows its true class in all images but at most one."""
    h, w = labels.shape
    out = []
    for k in range(count):
        im = labels.copy()
        x0 = (k * w) // count
        im[h // 2 + 20:h // 2 + 120, x0:x0 + w // (2 * count)] = 13
        out.append(im)
    return out


def test_calibrator_fuses_its_label_window(tmp_path, demo_scene):
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.engine.frames import fuse_labels
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal

    labels = read_label_image(demo_scene / "labels.png")
    images = passing_cars(labels, 3)
    fused = fuse_labels(images)
    assert np.array_equal(fused.labels, labels)  # the cars are outvoted everywhere
    camera = read_camera_info(demo_scene / "camera_info.yaml")
    header = conv.make_header(camera.frame_id, 1700000002.5)

    graph = RosGraph(tmp_path)
    ctx = graph.context()
    node = rclpy.create_node("label_window_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        proc = graph.start_node("calibrator", params={
            "map_file": str(demo_scene / "map.ply"), "label_window": 4,
            "diagnostics_period": 0.2, **CHEAP_ENGINE})
        watcher = DiagnosticsWatcher(node)
        info_pub = node.create_publisher(CameraInfo, "/camera/camera_info", qos.reliable(1))
        labels_pub = node.create_publisher(Image, "/camera/labels", qos.reliable(1))
        info = conv.model_to_camera_info(camera, header)
        timer = node.create_timer(0.3, lambda: info_pub.publish(info))
        spin_until(executor, lambda: watcher.get("calibrator").get("label_window") == "0/4", 60,
                   "the calibrator's diagnostics with an empty window")
        # one image at a time, each waited for: the window then holds exactly these three
        for k, im in enumerate(images, start=1):
            publish_until(executor, labels_pub, conv.numpy_to_image(im, "mono8", header),
                          lambda k=k: watcher.get("calibrator").get("label_window") == f"{k}/4",
                          60, f"label image {k} in the window", period=10.0)
        node.destroy_timer(timer)
        client = CalibrateClient(node)
        client.wait_for_server(30)
        out = client.call(executor, make_goal(read_pose(demo_scene / "initial.yaml")),
                          timeout=180)
        assert out.status == "succeeded", (out.status, out.result.message)
        match = proc.wait_for_log(r"3 label images fused per pixel \(([\d.]+) % agree", 10)
        assert float(match.group(1)) == pytest.approx(fused.agreement * 100, abs=0.051)
        assert fused.agreement < 0.99  # the cars made the images differ
        assert not re.search(r"Traceback", proc.log())
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())


@pytest.mark.parametrize("node_name", ["calibrator", "calibration_monitor"])
def test_a_window_of_zero_frames_is_refused_in_one_line(tmp_path, node_name):
    graph = RosGraph(tmp_path)
    try:
        proc = graph.start_node(node_name, params={"label_window": 0})
        assert proc.wait(60) != 0
        log = proc.log()
        assert "label_window must be >= 1 frames, got 0" in log
        assert "Traceback" not in log
    finally:
        graph.close()
