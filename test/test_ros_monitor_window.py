"""The calibration_monitor's label window (``label_window``) as a real process over DDS: each
drift check judges the per-pixel fusion of the last N label images the checks took, so cars
passing a static camera do not enter the check (the demo scene's map, its true calibration)."""

from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, publish_until, spin_until  # noqa: E402

pytestmark = pytest.mark.ros


def passing_cars(labels: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` copies of ``labels``, each with a car (trainId 13) in another place: every
    pixel shows its true class in all images but at most one."""
    h, w = labels.shape
    out = []
    for k in range(count):
        im = labels.copy()
        x0 = (k * w) // count
        # tall enough to cross class boundaries: the drift check compares the boundaries
        im[h // 4:3 * h // 4, x0:x0 + w // (2 * count)] = 13
        out.append(im)
    return out


def loss_at_calibration(demo_scene, labels: np.ndarray, reference: np.ndarray) -> float:
    """The check's loss at the calibration for ``labels`` counted from the check of
    ``reference`` (the monitor's first check), as the node computes it (the map prepared as the
    node prepares it, default engine and drift parameters): with a reference, the boundary
    charge between the two label images (engine/label_motion.py)."""
    from semcal_ros.engine.drift import DriftChecker, DriftParams, check_params
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.problem import mapping_for
    from semcal_ros.io.files import read_camera_info, read_pose
    from semcal_ros.io.ply import read_ply
    from semcal_ros.ros.held_map import EMPTY_CLOUD, HeldMap

    engine, drift = CalibrationParams(), DriftParams()
    held = HeldMap.from_cloud(read_ply(demo_scene / "map.ply").finite(),
                              mapping_for(check_params(engine, drift), None), "map", "file")
    checker = DriftChecker(EMPTY_CLOUD, read_camera_info(demo_scene / "camera_info.yaml"),
                           read_pose(demo_scene / "ground_truth.yaml"), engine, drift,
                           prepared=held.prepared)
    first = checker.check(reference)
    assert first.view is not None  # the reference keeps its image and the map's depth
    return float(checker.check(labels, reference=first).loss_calibrated)


@pytest.mark.slow
def test_the_monitor_checks_the_fusion_of_its_label_window(tmp_path, demo_scene):
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.engine.frames import fuse_labels
    from semcal_ros.io.files import read_camera_info, read_label_image
    from semcal_ros.ros.client import DiagnosticsWatcher

    labels = read_label_image(demo_scene / "labels.png")
    images = passing_cars(labels, 3)
    assert np.array_equal(fuse_labels(images).labels, labels)  # the cars are outvoted
    # the monitor's reference is its first check: the window holds images[0] alone then
    fused_loss = loss_at_calibration(demo_scene, labels, images[0])
    newest_loss = loss_at_calibration(demo_scene, images[-1], images[0])
    assert abs(newest_loss - fused_loss) > 1e-4  # the car in one image shows in its loss
    camera = read_camera_info(demo_scene / "camera_info.yaml")
    header = conv.make_header(camera.frame_id, 1700000002.5)

    graph = RosGraph(tmp_path)
    ctx = graph.context()
    node = rclpy.create_node("monitor_window_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        proc = graph.start_node("calibration_monitor", params={
            "map_file": str(demo_scene / "map.ply"), "period": 0.5, "label_window": 3,
            "diagnostics_period": 0.2, "calibration_file": str(demo_scene / "ground_truth.yaml")})
        watcher = DiagnosticsWatcher(node)
        diag = lambda: watcher.get("calibration_monitor")  # noqa: E731
        info_pub = node.create_publisher(CameraInfo, "/camera/camera_info", qos.reliable(1))
        labels_pub = node.create_publisher(Image, "/camera/labels", qos.reliable(1))
        info = conv.model_to_camera_info(camera, header)
        timer = node.create_timer(0.3, lambda: info_pub.publish(info))
        spin_until(executor, lambda: diag().get("label_window") == "0/3"
                   and diag().get("camera_info", "none") != "none", 60,
                   "the monitor's diagnostics with an empty window")
        # one image at a time, each taken by a check before the next is sent
        for k, im in enumerate(images, start=1):
            publish_until(executor, labels_pub, conv.numpy_to_image(im, "mono8", header),
                          lambda k=k: diag().get("label_window") == f"{k}/3", 60,
                          f"label image {k} in the window", period=10.0)
        checks = int(diag()["checks"])
        spin_until(executor, lambda: int(diag().get("checks", 0)) > checks + 1, 60,
                   "two more checks of the full window")
        node.destroy_timer(timer)
        # the check judged the fusion (no car), not the newest image (a car)
        assert float(diag()["loss_calibrated"]) == pytest.approx(fused_loss, abs=1e-5)
        assert diag()["level"] == "0", diag()  # OK: a static camera with passing cars
        assert "Traceback" not in proc.log()
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())

