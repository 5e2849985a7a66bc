"""The live path on real data: KITTI 00 frame 0 through the ROS nodes, ESPNetv2 in the loop.

A bag is written from the KITTI scene (scans 0-5 with their labels, lidar odometry, the camera
image and CameraInfo, repeated for 2 s). ``image_segmenter`` runs the ESPNetv2 export on the
image, ``map_builder`` builds the map from the scans, ``calibrator`` (with the scene's
calibrator.yaml: the paper's KITTI settings) takes both; the ``calibrate`` action is called from
the scene's perturbed initial pose and the result is compared with the ground truth (P2, Tr).

Checked exactly: the label image the node publishes is the offline segmenter's, the map the
calibrator holds is the offline map's size. The same goal is then sent with ``loss: mi`` (the
mutual-information loss, per goal), which must end within 20 cm / 0.5 deg of the truth. The
default loss's accuracy on these labels is not yet dependable (docs/real-data.md): beyond
50 cm / 1 deg the test ends as xfail with the measured errors instead of hiding them.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import reliable_overrides  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
KITTI = DATA / "kitti_odometry_00"
V2_WEIGHTS = DATA / "models" / "espnetv2_cityscapes" / "espnetv2_s_2.0_city_1024x512.npz"
pytestmark = [pytest.mark.ros, pytest.mark.skipif(
    not (KITTI / "image_2" / "000000.png").is_file() or not V2_WEIGHTS.is_file(),
    reason=f"shared real data not found at {DATA} (expected ../shared/data beside the checkout)")]
LIVE_LABELS = "/camera/labels_live"


def write_kitti_bag(scene: Path, bag: Path, camera_seconds: float = 2.0) -> int:
    """The scene's scans, lidar poses and camera messages as a bag; returns the scan count."""
    from scipy.spatial.transform import Rotation

    from semcal_ros.io import files
    from semcal_ros.io.scene_scans import open_scene_scans
    from semcal_tools.scenes.bag import CameraFrame, SceneBagWriter

    scans = open_scene_scans(scene)
    t0 = 1700000000.0
    camera = CameraFrame(files.read_camera_info(scene / "camera_info.yaml"),
                         files.read_rgb_image(scene / "image.png"),
                         files.read_label_image(scene / "labels.png"))
    writer = SceneBagWriter(bag, camera, camera_period=0.1)
    for i in range(len(scans)):
        cloud = scans.scan(i)
        pose = scans.poses[i]
        writer.add_scan(t0 + scans.stamps[i], pose[:3, 3], Rotation.from_matrix(pose[:3, :3])
                        .as_quat(), cloud.xyz, cloud.extra["intensity"], cloud.label)
    writer.close(t0 + scans.stamps[-1] + camera_seconds)
    return len(scans)


@pytest.mark.slow
def test_live_kitti_frame_with_espnetv2_in_the_loop(graph, tmp_path, exported):
    from sensor_msgs.msg import Image

    from semcal_ros.cli import main
    from semcal_ros.io import files, ply
    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal

    t_begin = time.monotonic()
    model, config = exported["espnetv2"]
    scene = tmp_path / "scene"
    assert main(["kitti-scene", "--kitti", str(KITTI), "--scans", "0-5", "--out", str(scene),
                 "--model", str(model), "--model-config", str(config),
                 "--threads", "2"]) == 0
    scans = write_kitti_bag(scene, tmp_path / "bag")

    segmenter = graph.start_node("image_segmenter", params={
        "model": str(model), "model_config": str(config),
        "runner.threads": 2}, remap={"image": "/camera/image_raw", "labels": LIVE_LABELS})
    builder = graph.start_node("map_builder", params={
        "mapping.icp": False, "mapping.remove_dynamic": False, "mapping.d_max": 60.0,
        "mapping.voxel": 0.1, "publish_period": 0.5, "queue_size": 20,
        # reliable scans and poses: the test waits for a map of every scan (best effort may
        # drop one under load, and a lost last pose holds the last scan back for good)
        **reliable_overrides("/lidar/points", "/lidar/odom")},
        remap={"scan": "/lidar/points", "odom": "/lidar/odom"})
    cal = graph.start_node("calibrator", params_file=scene / "calibrator.yaml",
                           remap={"camera/labels": LIVE_LABELS})
    ctx = graph.context()
    node = rclpy.create_node("kitti_live_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        live_labels: list = []
        node.create_subscription(Image, LIVE_LABELS, live_labels.append, qos.sensor(2))
        watcher = DiagnosticsWatcher(node)
        client = CalibrateClient(node)
        for proc in (segmenter, builder, cal):
            proc.wait_for_log("ready", 120)
        client.wait_for_server(30)
        # the bag's own /camera/labels has no subscriber (the calibrator takes the live ones):
        # a short wait, the other topics' subscribers are up already
        player = graph.start_node("bag_player", params={"bag": str(tmp_path / "bag"),
                                                        "wait_for_subscribers": 4.0})
        watcher.wait(executor, lambda: watcher.map_ready(scans) and live_labels, 60,
                     f"the map of all {scans} scans and a live label image")
        assert player.wait(20) == 0, player.log()

        # the node ran the real model: its labels are the offline segmenter's
        offline = files.read_label_image(scene / "labels.png")
        live = conv.image_to_labels(live_labels[-1])
        assert live.shape == offline.shape == (376, 1241)
        assert (live == offline).mean() > 0.999
        # the map the calibrator holds is the map kitti-scene built from the same scans (scans/
        # holds them as placed; stored as float32 and re-transformed, a few points change voxel)
        held = int(watcher.get("calibrator")["map_points"])
        built = len(ply.read_ply(scene / "map.ply"))
        assert abs(held - built) <= max(5, 1e-3 * built), (held, built)

        initial = files.read_pose(scene / "initial.yaml")
        truth = files.read_pose(scene / "ground_truth.yaml")
        out = client.call(executor, make_goal(initial, verification_starts=0), timeout=150)
        # the same goal with the mutual-information loss (docs/real-data.md: what survives a
        # real network's confusions), chosen per goal
        out_mi = client.call(executor, make_goal(initial, verification_starts=0, loss="mi"),
                             timeout=150)
    finally:
        executor.shutdown()
        node.destroy_node()
    assert out.status == "succeeded", out.result.message
    result = conv.pose_from_transform(out.result.transform)
    errors = (translation_error(result, truth), rotation_error_deg(result, truth))
    start = (translation_error(initial, truth), rotation_error_deg(initial, truth))
    summary = (f"live KITTI frame 0 with ESPNetv2: {errors[0] * 100:.1f} cm / {errors[1]:.3f} deg "
               f"from {start[0] * 100:.1f} cm / {start[1]:.3f} deg, "
               f"{time.monotonic() - t_begin:.0f} s in all; {out.result.message}")
    print(summary)
    assert out_mi.status == "succeeded", out_mi.result.message
    result_mi = conv.pose_from_transform(out_mi.result.transform)
    errors_mi = (translation_error(result_mi, truth), rotation_error_deg(result_mi, truth))
    print(f"the same with loss mi: {errors_mi[0] * 100:.1f} cm / {errors_mi[1]:.3f} deg; "
          f"{out_mi.result.message}")
    assert out.result.transform.child_frame_id == "camera_optical"
    # one start: within 20 cm / 0.5 deg. Measured 6.5 cm / 0.21 deg with the unbounded search,
    # 1.9 cm / 0.435 deg since the search stays within its bounds (a different path); single real
    # frames with mi: 0.4-1.5 deg over the KITTI frames (docs/real-data.md 3)
    assert errors_mi[0] < 0.20 and errors_mi[1] < 0.5, errors_mi
    if not (errors[0] < 0.5 and errors[1] < 1.0):
        pytest.xfail(f"engine not yet accurate on real labels: {summary}")
    assert errors[0] < 0.5 and errors[1] < 1.0
