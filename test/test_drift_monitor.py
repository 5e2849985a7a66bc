"""The calibration_monitor as a real process over DDS: an unchanged camera stays OK, a camera
turned by 0.4 deg and moved 5 cm is flagged (latched calibration/drift and /diagnostics) within two
periods after confirmation, and bad input is refused in one line while the node keeps working."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, spin_until  # noqa: E402

pytestmark = pytest.mark.ros

PERIOD = 1.0


@pytest.mark.slow
def test_monitor_flags_a_moved_camera_and_survives_bad_input(tmp_path: Path, demo_scene: Path):
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_interfaces.msg import CalibrationDrift
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.engine.pose import Pose
    from semcal_ros.ros.client import DiagnosticsWatcher
    from semcal_tools.scenes import SIZES
    from semcal_tools.scenes.generate import camera_view
    from geometry_msgs.msg import TransformStamped

    truth = read_pose(demo_scene / "ground_truth.yaml")
    moved = Pose.from_body_rpy_deg(truth.translation + [0.0, 0.05, 0.0],
                                   truth.body_rpy_deg() + [0.0, 0.0, 0.4])
    turned_labels = camera_view("junction", 0, "ideal", SIZES["small"], moved)
    camera = read_camera_info(demo_scene / "camera_info.yaml")
    header = conv.make_header(camera.frame_id, 1700000002.5)
    labels = {"same": conv.numpy_to_image(read_label_image(demo_scene / "labels.png"), "mono8",
                                          header),
              "turned": conv.numpy_to_image(turned_labels, "mono8", header)}
    info = conv.model_to_camera_info(camera, header)

    graph = RosGraph(tmp_path / "logs")
    ctx = graph.context()
    node = rclpy.create_node("monitor_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        proc = graph.start_node("calibration_monitor", params={
            "map_file": str(demo_scene / "map.ply"), "period": PERIOD, "confirm": 2,
            "calibration_file": str(demo_scene / "ground_truth.yaml")})
        drifts: list[Any] = []
        node.create_subscription(CalibrationDrift, "/calibration/drift", drifts.append,
                                 qos.latched())
        watcher = DiagnosticsWatcher(node)
        pub_labels = node.create_publisher(Image, "/camera/labels", qos.reliable(1))
        pub_info = node.create_publisher(CameraInfo, "/camera/camera_info", qos.reliable(1))
        pub_tf = node.create_publisher(TransformStamped, "/calibration/transform",
                                       qos.latched())
        showing = {"labels": labels["same"]}
        node.create_timer(0.2, lambda: (pub_labels.publish(showing["labels"]),
                                        pub_info.publish(info)))

        spin_until(executor, lambda: any("reference check" in m.message for m in drifts), 60,
                   "the monitor's reference check")
        n = len(drifts)
        spin_until(executor, lambda: len(drifts) >= n + 2, 60, "two more checks")
        unchanged = drifts[n:]
        assert all(m.level == CalibrationDrift.OK for m in unchanged), \
            [m.message for m in unchanged]
        assert all(m.camera_frame_id == camera.frame_id for m in unchanged)
        # its duration: a figure of bench_drift
        assert all(np.isfinite(m.seconds) and m.seconds > 0 for m in unchanged)

        # bad input: a label image of the wrong encoding, a calibration with NaN: one line each,
        # the node keeps what it held and keeps checking
        bad = conv.numpy_to_image(np.zeros((4, 4, 3), np.uint8), "rgb8", header)
        showing["labels"] = bad
        spin_until(executor, lambda: "ignoring label image" in proc.log(), 30,
                   "the monitor to refuse the rgb8 label image")
        nan = conv.transform_from_pose(truth, "map", camera.frame_id)
        nan.transform.translation.x = math.nan
        pub_tf.publish(nan)
        spin_until(executor, lambda: "not a finite pose" in proc.log(), 30,
                   "the monitor to refuse the NaN calibration")
        assert len([line for line in proc.log().splitlines() if "ignoring" in line]) == 2
        spin_until(executor, lambda: watcher.get("calibration_monitor").get("level") == "2",
                   30, "/diagnostics to show the refused input")
        assert "input_error.label image" in watcher.get("calibration_monitor")

        # the camera is knocked: 0.4 deg and 5 cm
        showing["labels"] = labels["turned"]
        n = len(drifts)
        spin_until(executor, lambda: any(m.level != CalibrationDrift.OK for m in drifts[n:]),
                   60, "the monitor to flag the moved camera")
        flagged = next(m for m in drifts[n:] if m.level != CalibrationDrift.OK)
        assert flagged.level in (CalibrationDrift.WARN, CalibrationDrift.ERROR), flagged.message
        assert 0.2 < flagged.drift_rotation_deg < 0.7, flagged.message
        assert flagged.loss_best < flagged.loss_calibrated
        assert drifts.index(flagged) - n <= 3  # confirmed on the 2nd check after the change
        spin_until(executor, lambda: watcher.get("calibration_monitor").get("level") in
                   ("1", "2") and "drift_deg" in watcher.get("calibration_monitor"), 30,
                   "the drift in /diagnostics")
        assert float(watcher.get("calibration_monitor")["drift_deg"]) > 0.2
        assert proc.running()
        # latched: a late subscriber gets the last verdict
        late: list[Any] = []
        node.create_subscription(CalibrationDrift, "/calibration/drift", late.append,
                                 qos.latched())
        spin_until(executor, lambda: bool(late), 30, "the latched drift message")
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())
