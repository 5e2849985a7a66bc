"""Bad inputs to the nodes other than the calibrator (its table is in test_ros_calibrator.py), to
the bag player and to the segmenters' models: one line naming the problem, the node alive, and
what it had built kept.

One map_builder process serves all of its cases and then has to keep building; model and bag
cases that stop a process at start run their processes side by side.
"""

from __future__ import annotations

import re
import struct
import time
from binascii import crc32
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402

from semcal_ros.engine.cloud import LabelledCloud  # noqa: E402
from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402

from ros_helpers import RosGraph, reliable_overrides, spin_until  # noqa: E402

pytestmark = pytest.mark.ros

T0 = 1000.0  # bag-like stamps: poses and scans every 0.1 s from here


# --- map_builder ------------------------------------------------------------------------------
class Feed:
    """A test node publishing scans and poses to one map_builder process."""

    def __init__(self, graph: RosGraph) -> None:
        from semcal_ros.ros.client import DiagnosticsWatcher

        self.ctx = graph.context()
        self.node = rclpy.create_node("feed", context=self.ctx)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.scans = self.node.create_publisher(PointCloud2, "/scan", qos.reliable(20))
        self.poses = self.node.create_publisher(PoseStamped, "/pose", qos.reliable(50))
        self.watcher = DiagnosticsWatcher(self.node)
        self.rng = np.random.default_rng(5)
        self.t = T0

    def diag(self) -> dict[str, str]:
        return self.watcher.get("map_builder")

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def pose(self, stamp: float, x: float = 0.0, q=(0.0, 0.0, 0.0, 1.0)) -> None:
        msg = PoseStamped(header=conv.make_header("map", stamp))
        msg.pose.position.x = x
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = q
        self.poses.publish(msg)

    def scan(self, stamp: float, xyz: np.ndarray | None = None) -> None:
        if xyz is None:  # a wall and a floor: building and road labels
            xyz = np.column_stack([self.rng.uniform(5, 30, 3000), self.rng.uniform(-10, 10, 3000),
                                   self.rng.uniform(-2, 5, 3000)])
        cloud = LabelledCloud(xyz, np.where(xyz[:, 2] > 0, 50, 40).astype(np.uint16))
        self.scans.publish(conv.cloud_to_pointcloud2(cloud, conv.make_header("lidar", stamp),
                                                     extra_fields=False))

    def step(self, n: int = 1) -> None:
        """``n`` good pose + scan pairs, 0.1 s of stream time apart."""
        for _ in range(n):
            self.t += 0.1
            self.pose(self.t, x=self.t - T0)
            self.scan(self.t)
            self.spin(0.03)

    def raw_scan(self, change: Callable[[PointCloud2], None]) -> None:
        cloud = LabelledCloud(np.ones((10, 3)), np.full(10, 50, np.uint16))
        msg = conv.cloud_to_pointcloud2(cloud, conv.make_header("lidar", self.t))
        change(msg)
        self.scans.publish(msg)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture(scope="module")
def builder(tmp_path_factory):
    graph = RosGraph(tmp_path_factory.mktemp("map_builder"))
    feed = None
    try:
        # reliable scans and poses (the QoS override parameters): the cases count the scans in
        # the map, and best effort may drop one while the machine is loaded
        proc = graph.start_node("map_builder", params={
            "mapping.icp": False, "mapping.remove_dynamic": False, "publish_period": 0.3,
            "queue_size": 5, "time_jump": 1.0, "jump_confirm": 3,
            **reliable_overrides("/scan", "/pose", depth=50)})
        feed = Feed(graph)
        proc.wait_for_log("ready", 120)
        spin_until(feed.executor, lambda: feed.scans.get_subscription_count() > 0
                   and feed.poses.get_subscription_count() > 0, 30, "the map builder to subscribe")
        # The first messages can go before the builder's side of the match is made (a publisher
        # sees its subscriber first; a volatile reader drops what came before it knew the
        # writer): feed until the map holds ten scans, whatever was lost on the way.
        deadline = time.monotonic() + 60
        while int(feed.diag().get("map_scans", 0)) < 10:
            assert time.monotonic() < deadline, \
                f"no map of ten scans after 60 s of feeding (diagnostics: {feed.diag()})"
            feed.step(1)
            feed.spin(0.1)
        yield proc, feed
    finally:
        if feed is not None:
            feed.close()
        graph.close()
        print(graph.logs())


def _drop_field(name: str) -> Callable[[PointCloud2], None]:
    def change(msg: PointCloud2) -> None:
        msg.fields = [f for f in msg.fields if f.name != name]
    return change


def _unknown_datatype(msg: PointCloud2) -> None:
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=99 if f.name == "x"
                             else f.datatype, count=1) for f in msg.fields]


def _truncate(msg: PointCloud2) -> None:
    msg.data = bytes(msg.data)[:7]


BUILDER_CASES: list[tuple[str, Callable[[Feed], None], str]] = [
    ("scan-without-label", lambda f: f.raw_scan(_drop_field("label")),
     "scan ignored: PointCloud2 has no 'label' field"),
    ("scan-without-x", lambda f: f.raw_scan(_drop_field("x")),
     "scan ignored: PointCloud2 has no x field"),
    ("scan-unknown-datatype", lambda f: f.raw_scan(_unknown_datatype),
     "PointCloud2 field 'x' has unknown datatype 99"),
    ("scan-truncated-data", lambda f: (f.raw_scan(_truncate), f.step()),
     "scan ignored: PointCloud2 data has 7 bytes, too few for 1 x 10 points"),
    ("scan-all-nan", lambda f: (f.pose(f.t + 0.05), f.scan(f.t + 0.05, np.full((400, 3), np.nan)),
                                f.step()),
     "has only NaN or infinite points (400); ignored"),
    ("scan-empty", lambda f: (f.pose(f.t + 0.05), f.scan(f.t + 0.05, np.zeros((0, 3))), f.step()),
     "has no points; ignored"),
    ("pose-nan", lambda f: f.pose(f.t, x=float("nan")), "pose ignored: pose contains NaN"),
    ("pose-not-unit", lambda f: f.pose(f.t, q=(0.0, 0.0, 0.0, 3.0)),
     "pose ignored: rotation is not a unit quaternion (norm 3)"),
    ("stray-old-scan", lambda f: (f.scan(f.t - 5.8), f.spin(0.1), f.step()),
     "is 5.8 s older than the newest"),
    ("stray-old-pose", lambda f: (f.pose(f.t - 7.0), f.spin(0.1), f.step()),
     "is 7.0 s older than the newest"),
]


@pytest.mark.parametrize("send,expected", [c[1:] for c in BUILDER_CASES],
                         ids=[c[0] for c in BUILDER_CASES])
def test_map_builder_refuses_bad_input(builder, send, expected):
    proc, feed = builder
    before = proc.log()
    scans_before, resets = int(feed.diag()["map_scans"]), feed.diag()["resets"]
    send(feed)
    deadline = time.monotonic() + 15
    while expected not in proc.log()[len(before):]:
        assert time.monotonic() < deadline, f"no /{expected}/ in the log:\n{proc.log()}"
        feed.spin(0.1)
    line = next(l for l in proc.log()[len(before):].splitlines() if expected in l)
    assert line.startswith("[WARN]"), line
    assert proc.running() and "Traceback" not in proc.log()
    feed.step()
    spin_until(feed.executor, lambda: int(feed.diag()["map_scans"]) > scans_before, 30,
               "the map to keep growing")
    assert feed.diag()["resets"] == resets  # a stray message resets nothing


def test_map_builder_says_poses_are_missing_then_catches_up(builder):
    proc, feed = builder
    accepted = int(feed.diag()["scans_accepted"])
    before = len(proc.log())
    # scans only: the pose stream has stopped. They go on until the node says so and drops scans
    # from its full queue (5) with the reason (it waits a second for poses before it says so)
    note = re.compile(r"\[WARN\].*scans dropped \(queue full\): no pose for")
    deadline = time.monotonic() + 60
    while not ("scans wait for their poses" in feed.diag().get("message", "")
               and note.search(proc.log()[before:])):
        assert time.monotonic() < deadline, f"no warning about missing poses:\n{proc.log()}"
        feed.t += 0.1
        feed.scan(feed.t)
        feed.spin(0.1)
    assert feed.diag()["level"] == "1"  # WARN
    feed.pose(feed.t + 0.05, x=feed.t - T0)  # poses again: the queued scans are built
    spin_until(feed.executor, lambda: int(feed.diag()["scans_accepted"]) >= accepted + 5, 30,
               "the queued scans to be built")
    feed.step()
    spin_until(feed.executor, lambda: "scans wait" not in feed.diag()["message"], 30,
               "the warning to clear")


def test_map_builder_resets_only_on_a_sustained_jump(builder):
    proc, feed = builder
    resets = int(feed.diag()["resets"])
    assert int(feed.diag()["map_scans"]) > 0
    feed.t -= 120.0  # time goes back for good: a bag started over
    feed.step(4)
    proc.wait_for_log(r"\[WARN\].*time jumped back 119\.\d s \(3 messages in a row", 30)
    spin_until(feed.executor, lambda: feed.diag().get("resets") == str(resets + 1)
               and feed.diag().get("map_scans") == "4", 30, "a new map of the new pass")
    assert feed.diag()["last_reset"].startswith("time jumped back")
    assert proc.running()


# --- segmenter models and bags: refused at start, one line --------------------------------------
def _write_bag(path: Path, crc: bool) -> None:
    """A small mcap bag (rosbags writes no chunk CRC; ``crc`` adds them as ros2 bag does)."""
    from test_ros_e2e import write_test_bag

    write_test_bag(path, "mcap", scans=6, points=500)
    if crc:
        mcap = next(path.glob("*.mcap"))
        data = bytearray(mcap.read_bytes())
        pos = 8  # after the magic: records of opcode (1), length (8), content
        while pos + 9 <= len(data) and data[pos] not in (0x02, 0x0F):  # footer, data end
            op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
            if op == 0x06:  # chunk: start, end, uncompressed size, crc, compression, records
                body = pos + 9
                size = struct.unpack_from("<Q", data, body + 16)[0]
                comp_len = struct.unpack_from("<I", data, body + 28)[0]
                rec_start = body + 32 + comp_len + 8
                struct.pack_into("<I", data, body + 24, crc32(data[rec_start:rec_start + size]))
            pos += 9 + length
        mcap.write_bytes(bytes(data))


def _damage(path: Path, offset_fraction: float = 0.5, n: int = 64) -> None:
    mcap = next(path.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    at = int(len(data) * offset_fraction)
    data[at:at + n] = b"\xa5" * n
    mcap.write_bytes(bytes(data))


def test_bag_checks(tmp_path):
    """The player verifies a bag before it plays: damaged chunks are found by their CRC (bags
    recorded by ros2 bag carry them) or by a message that no longer decodes."""
    from semcal_ros.ros.replay import verify_bag

    good = tmp_path / "good"
    _write_bag(good, crc=True)
    check = verify_bag(good)
    assert (check.errors, check.notes) == ([], [])
    damaged = tmp_path / "damaged"
    _write_bag(damaged, crc=True)
    _damage(damaged)
    check = verify_bag(damaged)
    assert len(check.errors) == 1 and "Chunk checksum mismatch" in check.errors[0], check
    plain = tmp_path / "plain"
    _write_bag(plain, crc=False)
    check = verify_bag(plain)
    assert check.errors == [] and check.notes == [
        "its chunks carry no CRC (written by rosbags?): damage inside message data cannot be "
        "detected"], check


def _startup_cases(tmp_path: Path) -> list[tuple[str, str, dict, str]]:
    import yaml

    from onnx_models import range_channel_model

    model = range_channel_model(tmp_path / "range.onnx", 0, [5.0, 20.0], 12.0, 12.0, 64, 2048)
    config = tmp_path / "range.yaml"
    config.write_text(yaml.safe_dump({"kind": "range", "height": 64, "width": 2048,
                                      "classes": ["pole", "building"], "means": [0] * 5,
                                      "stds": [1] * 5}))
    (tmp_path / "broken.onnx").write_bytes(b"this is no model")
    (tmp_path / "a_file").write_text("not a folder")
    (tmp_path / "image.yaml").write_text(yaml.safe_dump({"kind": "image"}))
    (tmp_path / "empty_bag").mkdir()
    (tmp_path / "bad_meta").mkdir()
    (tmp_path / "bad_meta" / "metadata.yaml").write_text("rosbag2_bagfile_information: [")
    damaged = tmp_path / "damaged_bag"
    _write_bag(damaged, crc=True)
    _damage(damaged)
    return [
        ("model-missing", "cloud_segmenter",
         {"model": str(tmp_path / "nope.onnx"), "model_config": str(config)},
         "parameter 'model': file not found"),
        ("model-not-onnx", "cloud_segmenter",
         {"model": str(tmp_path / "broken.onnx"), "model_config": str(config)},
         "broken.onnx: not a loadable ONNX model"),
        ("model-config-of-other-kind", "cloud_segmenter",
         {"model": str(model), "model_config": str(tmp_path / "image.yaml")},
         "image.yaml: image model config lacks input_width"),
        ("bag-folder-without-metadata", "bag_player", {"bag": str(tmp_path / "empty_bag")},
         "not a rosbag2 folder (no metadata.yaml)"),
        ("bag-metadata-not-yaml", "bag_player", {"bag": str(tmp_path / "bad_meta")},
         "cannot read bag"),
        ("bag-damaged-chunk", "bag_player", {"bag": str(damaged)},
         "Chunk checksum mismatch"),
        ("calibrator-bad-engine-parameter", "calibrator",
         {"engine.schedule.max_evaluations": [-1, 10, 10]}, "max_evaluations"),
        ("calibrator-missing-map-file", "calibrator", {"map_file": str(tmp_path / "no.ply")},
         "map file not found"),
        ("calibrator-overlay-file-under-a-file", "calibrator",
         {"overlay_file": str(tmp_path / "a_file" / "overlay.png")},
         "parameter 'overlay_file': " + str(tmp_path / "a_file" / "overlay.png")),
        ("map-builder-bad-extrinsic", "map_builder", {"lidar_extrinsic": [0.0, 0.0, 0.0]},
         "lidar_extrinsic must be [x, y, z, qx, qy, qz, qw]"),
    ]


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_MIDDLEWARE = re.compile(r"\[RTPS_[A-Z_]+ (Error|Warning|Info)\]")


def _own_lines(log: str) -> list[str]:
    """The lines a node printed itself: Fast DDS's own log lines are left out.

    When several participants start at once, Fast DDS can lose the race for a shared-memory port
    and logs "[RTPS_TRANSPORT_SHM Error] Failed init_port ...: open_and_lock_file failed" before
    it takes the next port (eProsima/Fast-DDS#6117, #2696); that line is the middleware's, not an
    error of the node, and it appears or not with the timing of the other processes.
    """
    return [line for line in log.splitlines()
            if not _MIDDLEWARE.search(_ANSI.sub("", line))]


@pytest.mark.slow
def test_nodes_refuse_bad_models_bags_and_parameters_at_start(tmp_path):
    cases = _startup_cases(tmp_path)
    graph = RosGraph(tmp_path / "logs")
    try:
        procs = [(name, graph.start_node(exe, params=params, name=name), expected)
                 for name, exe, params, expected in cases]
        failures = []
        for name, proc, expected in procs:
            code = proc.wait(60)
            log = proc.log().strip()
            errors = [l for l in _own_lines(log) if "error" in l.lower()]
            if code != 1 or expected not in log or "Traceback" in log or len(errors) != 1:
                failures.append(f"{name}: exit {code}, expected /{expected}/:\n{log}")
        assert not failures, "\n\n".join(failures)
    finally:
        graph.close()


def test_map_builder_resets_when_clock_goes_back(builder):
    """/clock going back by more than time_jump is a jump at once (a looping player, a
    simulator reset), no stray counting needed."""
    from rosgraph_msgs.msg import Clock

    proc, feed = builder
    resets = int(feed.diag()["resets"])
    clock = feed.node.create_publisher(Clock, "/clock", qos.reliable(10))
    spin_until(feed.executor, lambda: clock.get_subscription_count() > 0, 30,
               "the map builder to subscribe to /clock")
    clock.publish(Clock(clock=conv.seconds_to_stamp(feed.t)))
    feed.t -= 50.0
    clock.publish(Clock(clock=conv.seconds_to_stamp(feed.t)))  # in order after the first
    # the new pass's scans follow once the reset is applied (sent before, they could arrive
    # first on their own topic and make the jump by themselves)
    spin_until(feed.executor, lambda: feed.diag().get("resets") == str(resets + 1), 30,
               "the reset after /clock went back")
    feed.step(2)
    proc.wait_for_log(r"\[WARN\].*time jumped back 50\.0 s \(/clock went back", 30)
    spin_until(feed.executor, lambda: feed.diag().get("resets") == str(resets + 1)
               and feed.diag().get("map_scans") == "2", 30, "a new map after /clock went back")
