"""A moving rig's frames calibrated by the calibrator process (``rig_frames``), over DDS.

Real data end to end: two KITTI 00 frames (000556 and 002780 of ``kitti_odometry_00_frames``,
2.2 km apart on the drive). Their raw HDL-64E scans go through a ``cloud_segmenter`` process
(the geometric labeller) to the calibrator's ``labelled_points``; their ESPNetv2 label images
(the real network) and the CameraInfo go to the calibrator's camera topics, each image stamped
as its scan. A goal from this process gives the camera's initial pose in the lidar frame; the
result is checked against KITTI's P2 / Tr. On the way: a label image with no scan near its
stamp is counted unpaired, an unusable scan is refused in one line and the pairs held stay, and
a goal in the wrong frame is aborted naming it.

Needs ``../shared/data`` beside the checkout (skipped without).
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from semcal_ros.cli import main  # noqa: E402
from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, publish_until, reliable_overrides, spin_until  # noqa: E402

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
FRAMES = ROOT.parent / "shared" / "data" / "kitti_odometry_00_frames"
RIG = {"000556": 1000.0, "002780": 1222.4}  # frame -> stamp given to its scan and image
LIDAR, CAMERA = "velodyne", "camera_2_optical"


@pytest.fixture(scope="module")
def rig_scenes(tmp_path_factory, exported) -> Path:
    """The two frames as real-scene writes them (ESPNetv2 labels, the truth, the shared start)."""
    if not (FRAMES / "image_2" / "000556.png").is_file():
        pytest.skip(f"shared real data not found at {FRAMES}")
    model, config = exported["espnetv2"]
    out = tmp_path_factory.mktemp("rig") / "rig"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main([str(a) for a in [
            "real-scene", "--image", *(FRAMES / "image_2" / f"{f}.png" for f in RIG),
            "--scans", *(FRAMES / "velodyne" / f"{f}.bin" for f in RIG),
            "--calib", FRAMES / "calib.txt", "--cloud-labels", "geometric",
            "--model", model, "--model-config", config, "--threads", 1, "--out", out]]) == 0
    return out


def raw_scan(frame: str, stamp: float):
    """The KITTI scan as a lidar driver publishes it: x, y, z, intensity."""
    from semcal_ros.io.lidar_scans import read_lidar_scan

    cloud = read_lidar_scan(FRAMES / "velodyne" / f"{frame}.bin")
    arr = np.zeros(len(cloud), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                      ("intensity", "<f4")])
    for i, axis in enumerate("xyz"):
        arr[axis] = cloud.xyz[:, i]
    arr["intensity"] = cloud.extra["intensity"]
    return conv.array_to_pointcloud2(arr, conv.make_header(LIDAR, stamp))


@pytest.mark.slow
def test_the_calibrator_calibrates_a_moving_rig_over_its_last_frames(tmp_path, rig_scenes):
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal

    first = rig_scenes / "000556"
    camera = read_camera_info(first / "camera_info.yaml")
    truth, initial = read_pose(first / "ground_truth.yaml"), read_pose(first / "initial.yaml")
    graph = RosGraph(tmp_path)
    ctx = graph.context()
    node = rclpy.create_node("rig_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        graph.start_node("cloud_segmenter", params={
            "method": "geometric", **reliable_overrides("/points", depth=4),
            "qos_overrides./labelled_points.publisher.reliability": "reliable"})
        # the first scene's calibrator.yaml (KITTI: road and sidewalk merged, parked cars
        # count, the rows no lidar point reaches left out) for every frame
        proc = graph.start_node("calibrator", params_file=first / "calibrator.yaml", params={
            "rig_frames": 2, "diagnostics_period": 0.2,
            **reliable_overrides("/labelled_points", "/camera/labels", depth=4)})
        watcher = DiagnosticsWatcher(node)
        diag = lambda: watcher.get("calibrator")  # noqa: E731
        info_pub = node.create_publisher(CameraInfo, "/camera/camera_info", qos.reliable(1))
        labels_pub = node.create_publisher(Image, "/camera/labels", qos.reliable(4))
        points_pub = node.create_publisher(PointCloud2, "/points", qos.reliable(4))
        info = conv.model_to_camera_info(camera, conv.make_header(CAMERA, 0.0))
        timer = node.create_timer(0.3, lambda: info_pub.publish(info))
        spin_until(executor, lambda: diag().get("rig_pairs") == "0/2"
                   and diag().get("camera_info", "none") != "none", 60,
                   "the calibrator's diagnostics with its CameraInfo and no pairs")
        assert diag().get("map_source") == "none" and diag()["level"] == "1"  # WARN: no pairs
        assert "0 of rig_frames 2 label image + labelled scan pairs held" in diag()["message"]

        def labels_msg(frame: str, stamp: float):
            return conv.numpy_to_image(read_label_image(rig_scenes / frame / "labels.png"),
                                       "mono8", conv.make_header(CAMERA, stamp))

        for k, (frame, stamp) in enumerate(RIG.items(), start=1):
            publish_until(executor, points_pub, raw_scan(frame, stamp),
                          lambda k=k: diag().get("rig_scans_held") == f"{k}/10", 120,
                          f"scan {frame} labelled and held", period=15.0)
            if k == 1:  # an image 1 s from any scan: counted, not paired, not an error
                publish_until(executor, labels_pub, labels_msg(frame, stamp - 1.0),
                              lambda: diag().get("rig_unpaired") == "1", 60,
                              "the stray image counted", period=10.0)
                assert "the nearest held scan is 1.000 s away" in diag()["rig_last_unpaired"]
            publish_until(executor, labels_pub, labels_msg(frame, stamp),
                          lambda k=k: diag().get("rig_pairs") == f"{k}/2", 60,
                          f"image {frame} paired", period=10.0)
        node.destroy_timer(timer)

        # an unusable scan: one line, the pairs held stay
        bad = np.zeros(10, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
        bad_pub = node.create_publisher(PointCloud2, "/labelled_points", qos.reliable(4))
        publish_until(executor, bad_pub, conv.array_to_pointcloud2(
            bad, conv.make_header(LIDAR, 1300.0)),
            lambda: "input_error.labelled_scan" in diag(), 60, "the bad scan refused",
            period=10.0)
        assert diag()["rig_pairs"] == "2/2" and diag()["rig_scans_held"] == "2/10"
        proc.wait_for_log(r"ignoring labelled scan on '/labelled_points': the scan has no "
                          r"'label' field", 10)

        client = CalibrateClient(node)
        client.wait_for_server(30)
        wrong = client.call(executor, make_goal(initial), timeout=60)  # frame 'map'
        assert wrong.status == "aborted"
        assert "initial_pose is in frame 'map' but the rig's scans are in 'velodyne'" in \
            wrong.result.message
        out = client.call(executor, make_goal(initial, map_frame=LIDAR, verification_starts=1),
                          timeout=600)
        assert out.status == "succeeded", (out.status, out.result.message)
        t = out.result.transform
        assert (t.header.frame_id, t.child_frame_id) == (LIDAR, CAMERA)
        result = conv.pose_from_transform(t)
        print(f"rig of 2: {translation_error(result, truth) * 100:.1f} cm / "
              f"{rotation_error_deg(result, truth):.3f} deg from the truth, start "
              f"{translation_error(initial, truth) * 100:.1f} cm off; {out.result.message}")
        assert translation_error(initial, truth) > 0.5  # the search had work to do
        assert translation_error(result, truth) < 0.20, out.result.message
        assert rotation_error_deg(result, truth) < 1.0, out.result.message
        log = proc.log()
        assert "against 2 frames of the rig in 'velodyne' (scans of 120960, 119650 points)" \
            in log
        assert "one-scan maps of 48655, 48447 points" in log  # as real-scene's map.ply
        for stamp in RIG.values():
            assert f"labels {stamp:.3f} s + scan {stamp:.3f} s: loss" in log
        assert "Traceback" not in graph.logs()
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())
