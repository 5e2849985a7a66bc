"""End-to-end: real node processes talking over DDS on localhost, one ROS domain per test."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from nav_msgs.msg import Odometry  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, spin_until  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture
def graph(tmp_path):
    g = RosGraph(tmp_path)
    yield g
    g.close()
    print(g.logs())  # shown by pytest only when the test failed


# --- bag replay ------------------------------------------------------------------------------
def write_test_bag(path: Path, storage: str, scans: int = 30, hz: float = 20.0,
                   points: int = 20000, t0: float = 1700000000.0) -> list[np.ndarray]:
    """A bag with PointCloud2 scans and Odometry, written with rosbags; returns the scans."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    rng = np.random.default_rng(4)
    written = []
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        c_points = writer.add_connection("/test/points", "sensor_msgs/msg/PointCloud2",
                                         typestore=ts)
        c_odom = writer.add_connection("/test/odom", "nav_msgs/msg/Odometry", typestore=ts)
        dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u2")])
        fields = [t["sensor_msgs/msg/PointField"](name=n, offset=dtype.fields[n][1],
                                                   datatype=4 if n == "label" else 7, count=1)
                  for n in dtype.names]
        for i in range(scans):
            stamp = t0 + i / hz
            ns = int(round(stamp * 1e9))
            header = t["std_msgs/msg/Header"](
                stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                frame_id="lidar")
            arr = np.zeros(points, dtype)
            for a in "xyz":
                arr[a] = rng.normal(size=points)
            arr["label"] = i
            written.append(arr)
            cloud = t["sensor_msgs/msg/PointCloud2"](
                header=header, height=1, width=points, fields=fields, is_bigendian=False,
                point_step=dtype.itemsize, row_step=dtype.itemsize * points,
                data=np.frombuffer(arr.tobytes(), np.uint8), is_dense=True)
            writer.write(c_points, ns, ts.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2"))
            g = "geometry_msgs/msg/"
            odom = t["nav_msgs/msg/Odometry"](
                header=header, child_frame_id="base_link",
                pose=t[g + "PoseWithCovariance"](
                    pose=t[g + "Pose"](position=t[g + "Point"](float(i), 0.0, 0.0),
                                       orientation=t[g + "Quaternion"](0.0, 0.0, 0.0, 1.0)),
                    covariance=np.zeros(36)),
                twist=t[g + "TwistWithCovariance"](
                    twist=t[g + "Twist"](linear=t[g + "Vector3"](0.0, 0.0, 0.0),
                                         angular=t[g + "Vector3"](0.0, 0.0, 0.0)),
                    covariance=np.zeros(36)))
            writer.write(c_odom, ns + 1000, ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))
    return written


@pytest.mark.parametrize("storage,door", [("mcap", "node"), ("sqlite3", "cli")])
def test_bag_replay_delivers_everything_with_timing_and_clock(graph, tmp_path, storage, door):
    bag = tmp_path / f"bag_{storage}"
    scans = write_test_bag(bag, storage)
    ctx = graph.context()
    node = rclpy.create_node("replay_listener", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    got_clouds, got_odom, clock = [], [], []
    node.create_subscription(PointCloud2, "/test/points",
                             lambda m: got_clouds.append((time.monotonic(), m)),
                             qos.reliable(50))
    node.create_subscription(Odometry, "/test/odom", got_odom.append, qos.reliable(50))
    node.create_subscription(Clock, "/clock", lambda m: clock.append(
        conv.stamp_to_seconds(m.clock)), qos.reliable(100))
    rate = 2.0
    if door == "node":
        player = graph.start_node("bag_player", params={"bag": str(bag), "rate": rate,
                                                        "clock": True})
    else:
        player = graph.start("semcal_replay", "semcal", "replay", str(bag), "--rate", str(rate),
                             "--clock")
    try:
        spin_until(executor, lambda: len(got_clouds) == 30 and len(got_odom) == 30, 30,
                   "30 clouds and 30 odometry messages")
        assert player.wait(15) == 0, player.log()
        executor.spin_once(timeout_sec=0.2)
    finally:
        executor.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    for (_, msg), arr in zip(got_clouds, scans):
        np.testing.assert_array_equal(conv.pointcloud2_to_array(msg), arr)
    assert [o.pose.pose.position.x for o in got_odom] == [float(i) for i in range(30)]
    # 29 intervals of 50 ms of bag time at rate 2: ~0.725 s of wall time between first and last.
    spread = got_clouds[-1][0] - got_clouds[0][0]
    assert 0.5 < spread < 1.5, spread
    assert len(clock) >= 30 and np.all(np.diff(clock) >= 0)
    assert 1700000000.0 <= clock[0] and clock[-1] <= 1700000000.0 + 29 / 20.0 + 1e-5  # last: odometry, 1 us later


def test_bag_player_reports_a_missing_bag(graph, tmp_path):
    player = graph.start_node("bag_player", params={"bag": str(tmp_path / "nope")})
    assert player.wait(20) == 1
    assert "bag not found" in player.log()
