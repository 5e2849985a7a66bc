"""ROS message conversions, QoS and parameter helpers (in-process; no DDS traffic between nodes)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField  # noqa: E402

from semcal_ros.engine.camera import CameraModel  # noqa: E402
from semcal_ros.engine.cloud import LabelledCloud  # noqa: E402
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error  # noqa: E402
from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros import qos  # noqa: E402
from semcal_ros.ros.params import declare_and_read, read_dataclass  # noqa: E402


def _cloud(n: int = 500, seed: int = 0) -> LabelledCloud:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-50, 50, (n, 3)).astype(np.float32).astype(np.float64)
    label = rng.choice([40, 48, 50, 70, 80, 259], n).astype(np.uint16)
    return LabelledCloud(xyz, label, {"intensity": rng.random(n).astype(np.float32)})


# --- PointCloud2 -----------------------------------------------------------------------------
def test_cloud_round_trip_through_cdr():
    cloud = _cloud()
    msg = conv.cloud_to_pointcloud2(cloud, conv.make_header("map", 12.5))
    back = conv.pointcloud2_to_cloud(deserialize_message(serialize_message(msg), PointCloud2))
    np.testing.assert_array_equal(back.xyz, cloud.xyz)
    np.testing.assert_array_equal(back.label, cloud.label)
    np.testing.assert_array_equal(back.extra["intensity"], cloud.extra["intensity"])
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "label"]
    assert msg.fields[-1].datatype == PointField.UINT16
    assert msg.header.frame_id == "map" and conv.stamp_to_seconds(msg.header.stamp) == 12.5


def test_cloud_any_field_order_offsets_and_padding():
    """A driver layout: intensity first, padding, float64 xyz, 32-bit label with an instance id."""
    n = 64
    rng = np.random.default_rng(1)
    dtype = np.dtype({"names": ["intensity", "z", "x", "y", "label", "ring"],
                      "formats": ["<f4", "<f8", "<f8", "<f8", "<u4", "<u2"],
                      "offsets": [0, 8, 16, 24, 36, 42], "itemsize": 48})
    arr = np.zeros(n, dtype)
    for name in ("x", "y", "z"):
        arr[name] = rng.normal(size=n) * 10
    arr["intensity"] = rng.random(n)
    arr["ring"] = np.arange(n) % 16
    semantic = rng.choice([40, 50, 70], n).astype(np.uint32)
    arr["label"] = semantic | (np.arange(n, dtype=np.uint32) << 16)  # instance in the high half
    msg = conv.array_to_pointcloud2(arr, conv.make_header("lidar"))
    assert [f.offset for f in msg.fields] == [0, 8, 16, 24, 36, 42] and msg.point_step == 48
    cloud = conv.pointcloud2_to_cloud(deserialize_message(serialize_message(msg), PointCloud2))
    np.testing.assert_array_equal(cloud.xyz, np.stack([arr["x"], arr["y"], arr["z"]], 1))
    np.testing.assert_array_equal(cloud.label, semantic)
    assert set(cloud.extra) == {"intensity", "ring"}
    np.testing.assert_array_equal(cloud.extra["ring"], arr["ring"])


def test_cloud_big_endian_and_row_padding():
    """An organised 2 x 3 cloud, big endian, with 4 bytes of padding after each row."""
    xyz = np.arange(18, dtype=np.float32).reshape(6, 3)
    rows = []
    for r in range(2):
        rows.append(xyz[r * 3:(r + 1) * 3].astype(">f4").tobytes() + b"\0\0\0\0")
    msg = PointCloud2(height=2, width=3, is_bigendian=True, point_step=12, row_step=40,
                      fields=[PointField(name=a, offset=4 * i, datatype=PointField.FLOAT32,
                                         count=1) for i, a in enumerate("xyz")])
    msg.data = b"".join(rows)
    cloud = conv.pointcloud2_to_cloud(msg)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    assert cloud.label is None


def test_cloud_errors_name_the_problem():
    msg = PointCloud2(height=1, width=2, point_step=8, row_step=16,
                      fields=[PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1),
                              PointField(name="y", offset=4, datatype=PointField.FLOAT32,
                                         count=1)])
    msg.data = bytes(16)
    with pytest.raises(ValueError, match=r"no z field \(fields: x, y\)"):
        conv.pointcloud2_to_cloud(msg)
    msg.data = bytes(10)
    with pytest.raises(ValueError, match="too few"):
        conv.pointcloud2_to_array(msg)
    msg.fields[1].offset = 6
    with pytest.raises(ValueError, match="does not fit"):
        conv.pointcloud2_dtype(msg)
    xyz_only = conv.cloud_to_pointcloud2(LabelledCloud(np.zeros((3, 3))), conv.make_header("m"))
    with pytest.raises(ValueError, match="no 'label' field"):
        conv.pointcloud2_to_cloud(xyz_only, require_label=True)


def test_empty_cloud():
    msg = conv.cloud_to_pointcloud2(LabelledCloud(np.zeros((0, 3)), np.zeros(0, np.uint16)),
                                    conv.make_header("map"))
    back = conv.pointcloud2_to_cloud(msg)
    assert len(back) == 0 and back.label is not None


# --- Image -----------------------------------------------------------------------------------
def test_image_rgb_bgr_mono_round_trips():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    header = conv.make_header("camera_optical", 3.25)
    msg = deserialize_message(serialize_message(conv.numpy_to_image(rgb, "rgb8", header)), Image)
    np.testing.assert_array_equal(conv.image_to_rgb(msg), rgb)
    bgr = conv.numpy_to_image(np.ascontiguousarray(rgb[:, :, ::-1]), "bgr8", header)
    np.testing.assert_array_equal(conv.image_to_rgb(bgr), rgb)
    labels = rng.integers(0, 19, (7, 5), dtype=np.uint8)
    np.testing.assert_array_equal(
        conv.image_to_labels(conv.numpy_to_image(labels, "mono8", header)), labels)


def test_image_with_row_padding():
    labels = np.arange(12, dtype=np.uint8).reshape(3, 4)
    msg = Image(height=3, width=4, encoding="mono8", step=8)
    msg.data = b"".join(row.tobytes() + b"\xff" * 4 for row in labels)
    np.testing.assert_array_equal(conv.image_to_labels(msg), labels)


def test_image_errors_name_the_problem():
    msg = Image(height=2, width=2, encoding="rgba16", step=16)
    msg.data = bytes(32)
    with pytest.raises(ValueError, match="unsupported image encoding 'rgba16'"):
        conv.image_to_numpy(msg)
    msg = Image(height=2, width=2, encoding="rgb8", step=6)
    msg.data = bytes(7)
    with pytest.raises(ValueError, match="too few"):
        conv.image_to_numpy(msg)
    msg.data = bytes(12)
    with pytest.raises(ValueError, match="expected a mono8 label image, got encoding 'rgb8'"):
        conv.image_to_labels(msg)
    with pytest.raises(ValueError, match="3 channels"):
        conv.numpy_to_image(np.zeros((2, 2), np.uint8), "rgb8", conv.make_header("c"))


# --- CameraInfo ------------------------------------------------------------------------------
def test_camera_info_round_trip_projects_identically():
    cam = CameraModel(640, 400, np.array([[500.0, 0, 319.5], [0, 505.0, 199.5], [0, 0, 1]]),
                      np.array([-0.1, 0.02, 0.001, -0.002, 0.0]), frame_id="cam_optical")
    msg = deserialize_message(serialize_message(conv.model_to_camera_info(cam)), CameraInfo)
    back = conv.camera_info_to_model(msg)
    assert (back.width, back.height, back.frame_id) == (640, 400, "cam_optical")
    pts = np.random.default_rng(3).uniform([-5, -3, 2], [5, 3, 30], (200, 3))
    np.testing.assert_allclose(back.project(pts)[0], cam.project(pts)[0], atol=1e-9)


def test_camera_info_errors():
    msg = conv.model_to_camera_info(
        CameraModel(10, 10, np.array([[5.0, 0, 5], [0, 5, 5], [0, 0, 1]]), np.zeros(5)))
    msg.distortion_model = "fov"
    with pytest.raises(ValueError, match="unsupported distortion model 'fov'"):
        conv.camera_info_to_model(msg)
    msg.distortion_model = "plumb_bob"
    msg.binning_x = 2
    with pytest.raises(ValueError, match="binning"):
        conv.camera_info_to_model(msg)
    with pytest.raises(ValueError, match="not calibrated"):
        conv.camera_info_to_model(CameraInfo(width=10, height=10))


# --- poses -----------------------------------------------------------------------------------
def test_pose_and_transform_round_trips():
    pose = Pose.from_body_rpy_deg([10.0, -4.0, 6.5], [1.0, 12.0, -130.0])
    back = conv.pose_from_msg(conv.pose_to_msg(pose))
    assert translation_error(back, pose) < 1e-12 and rotation_error_deg(back, pose) < 1e-9
    tf = conv.transform_from_pose(pose, "map", "camera_optical", 100.000000001)
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "camera_optical")
    assert (tf.header.stamp.sec, tf.header.stamp.nanosec) == (100, 1)
    back = conv.pose_from_transform(tf)
    assert translation_error(back, pose) < 1e-12 and rotation_error_deg(back, pose) < 1e-9


def test_stamped_poses_from_odometry_and_pose_stamped():
    pose = Pose(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, np.sin(0.3), np.cos(0.3)]))
    odom = Odometry(header=conv.make_header("map", 5.5))
    odom.pose.pose = conv.pose_to_msg(pose)
    stamp, got, frame = conv.stamped_pose(odom)
    assert (stamp, frame) == (5.5, "map") and translation_error(got, pose) == 0
    ps = PoseStamped(header=conv.make_header("odom", 7.0), pose=conv.pose_to_msg(pose))
    assert conv.stamped_pose(ps)[0] == 7.0
    ps.pose.orientation.w = 2.0
    with pytest.raises(ValueError, match="unit quaternion"):
        conv.stamped_pose(ps)
    with pytest.raises(ValueError, match="no pose in a Image"):
        conv.stamped_pose(Image())


def test_seconds_to_stamp_rounding():
    for seconds in (0.0, 1.9999999999, 1700000000.123456789, 2.5e-10):
        stamp = conv.seconds_to_stamp(seconds)
        assert 0 <= stamp.nanosec < 1_000_000_000
        assert abs(conv.stamp_to_seconds(stamp) - seconds) < 1e-6


# --- QoS and parameters ----------------------------------------------------------------------
def test_qos_profiles():
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    assert qos.sensor().reliability == ReliabilityPolicy.BEST_EFFORT
    assert qos.latched().durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos.latched().reliability == ReliabilityPolicy.RELIABLE


@dataclass
class _Inner:
    voxel: float = 0.1
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class _Params:
    topic: str = "lidar/points"
    depth: int = 5
    enabled: bool = True
    inner: _Inner = field(default_factory=_Inner)

    def __post_init__(self) -> None:
        if self.depth < 1:
            raise ValueError("depth must be at least 1")


@pytest.fixture
def ros_context():
    contexts = []

    def make(*ros_args: str):
        ctx = rclpy.Context()
        rclpy.init(args=["test", "--ros-args", *ros_args], context=ctx)
        contexts.append(ctx)
        return ctx

    yield make
    for ctx in contexts:
        ctx.try_shutdown()


def test_params_declared_from_dataclass_and_overridden(ros_context):
    ctx = ros_context("-p", "inner.voxel:=2", "-p", "inner.center:=[1.0, 2.0, 3.0]",
                      "-p", "topic:=scan")
    node = rclpy.create_node("params_test", context=ctx)
    try:
        params = declare_and_read(node, _Params())
        assert params.inner.voxel == 2.0 and isinstance(params.inner.voxel, float)
        assert params.inner.center == (1.0, 2.0, 3.0)
        assert params.topic == "scan" and params.depth == 5 and params.enabled is True
        assert node.has_parameter("inner.center") and node.has_parameter("enabled")
        node.set_parameters([rclpy.parameter.Parameter("depth", value=0)])
        with pytest.raises(ValueError, match="depth must be at least 1"):
            read_dataclass(node, _Params())
    finally:
        node.destroy_node()


def test_params_bad_value_is_named(ros_context):
    ctx = ros_context("-p", "depth:=many")
    node = rclpy.create_node("params_bad", context=ctx)
    try:
        with pytest.raises(ValueError, match="params_bad: parameter 'depth': cannot use 'many'"):
            declare_and_read(node, _Params())
    finally:
        node.destroy_node()


# --- parameter files -------------------------------------------------------------------------
def _node_param_files():
    from semcal_ros.ros.nodes.cloud_segmenter import CloudSegmenterParams
    from semcal_ros.ros.nodes.image_segmenter import ImageSegmenterParams
    from semcal_ros.ros.nodes.map_builder import MapBuilderNodeParams
    from semcal_ros.ros.replay import ReplayParams

    return [("bag_player", ReplayParams()), ("image_segmenter", ImageSegmenterParams()),
            ("cloud_segmenter", CloudSegmenterParams()), ("map_builder", MapBuilderNodeParams())]


@pytest.mark.parametrize("node,defaults", _node_param_files(), ids=lambda v: str(v)[:20])
def test_config_file_matches_node_parameters(node, defaults):
    """Every key of config/<node>.yaml is a parameter of the node, every value fits it, and
    every parameter of the node itself is in the file (groups owned by library modules,
    ``mapping.*`` and ``runner.*``, may gain fields the file does not list yet)."""
    from pathlib import Path

    from semcal_ros.engine.config import apply_flat, dataclass_fields_flat, load_node_params

    path = Path(__file__).resolve().parents[1] / "config" / f"{node}.yaml"
    flat = load_node_params(path, node)
    known = set(dataclass_fields_flat(defaults))
    assert not set(flat) - known, f"unknown keys in {path.name}"
    missing = {k for k in known - set(flat) if not k.startswith(("mapping.", "runner."))}
    assert not missing, f"{path.name} does not list {sorted(missing)}"
    apply_flat(defaults, flat)  # raises on a value that does not fit


def test_add_label_field_keeps_every_field_and_replaces_a_label():
    from semcal_ros.ros.nodes.cloud_segmenter import add_label_field

    dtype = np.dtype({"names": ["label", "x", "y", "z", "t"],
                      "formats": ["<u4", "<f4", "<f4", "<f4", "<f8"],
                      "offsets": [0, 8, 12, 16, 24], "itemsize": 40})
    points = np.zeros(4, dtype)
    points["x"], points["t"], points["label"] = [1, 2, 3, 4], [0.5] * 4, 99
    out = add_label_field(points, np.array([40, 50, 70, 80], np.uint16))
    assert out.dtype.names == ("x", "y", "z", "t", "label") and out.dtype["label"] == np.uint16
    np.testing.assert_array_equal(out["x"], points["x"])
    np.testing.assert_array_equal(out["t"], points["t"])
    np.testing.assert_array_equal(out["label"], [40, 50, 70, 80])


def test_calibrator_config_file_holds_only_node_and_engine_parameters():
    from pathlib import Path

    from semcal_ros.engine.config import apply_flat, dataclass_fields_flat, load_node_params
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.ros.nodes.calibrator import CalibratorNodeParams

    flat = load_node_params(Path(__file__).resolve().parents[1] / "config" / "calibrator.yaml",
                            "calibrator")
    node, engine = CalibratorNodeParams(), CalibrationParams()
    engine_flat = {k[len("engine."):]: v for k, v in flat.items() if k.startswith("engine.")}
    node_flat = {k: v for k, v in flat.items() if not k.startswith("engine.")}
    assert engine_flat, "the engine's parameters stand under 'engine:'"
    assert set(node_flat) <= set(dataclass_fields_flat(node)), node_flat
    assert set(engine_flat) <= set(dataclass_fields_flat(engine)), engine_flat
    apply_flat(node, node_flat, strict=True)
    apply_flat(engine, engine_flat, strict=True)


# --- the Calibrate goal ----------------------------------------------------------------------
def test_goal_options_become_engine_parameters():
    from semcal_interfaces.action import Calibrate

    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.ros.calibrate_goal import goal_params
    from semcal_ros.ros.client import make_goal

    defaults = CalibrationParams()
    initial = Pose.from_body_rpy_deg([0.0, 0.0, 5.0], [0.0, 10.0, 0.0])
    assert goal_params(make_goal(initial), defaults) == defaults
    goal = make_goal(initial, bound_translation_m=(1.0, 0.0, 0.5), bound_rpy_deg=(0.0, 3.0, 0.0),
                     verification_starts=0, roll=Calibrate.Goal.ROLL_FREE,
                     yaw_search=Calibrate.Goal.YAW_SEARCH_ON, loss="huber")
    p = goal_params(goal, defaults)
    assert p.search.bound_xyz == (1.0, defaults.search.bound_xyz[1], 0.5)
    assert p.search.bound_pitch_deg == 3.0
    assert p.search.bound_yaw_deg == defaults.search.bound_yaw_deg
    assert p.search.free_roll and p.search.yaw_search
    assert p.verification.starts == 0 and p.loss.kind == "huber"


def test_goal_request_checks_inputs():
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.ros.calibrate_goal import Inputs, goal_request
    from semcal_ros.ros.client import make_goal
    from semcal_ros.ros.held_map import HeldMap

    cam = CameraModel(64, 48, np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]), np.zeros(5),
                      frame_id="cam")
    inputs = Inputs(HeldMap.from_cloud(_cloud(), LabelMapping(), "map", "test"), "map",
                    np.zeros((40, 64), np.uint8), "cam", cam)
    initial = Pose.from_body_rpy_deg([0.0, 0.0, 5.0], [0.0, 10.0, 0.0])
    with pytest.raises(ValueError, match="label image is 64x40 but CameraInfo says 64x48"):
        goal_request(make_goal(initial), inputs, CalibrationParams(), 0)
    inputs.labels = np.zeros((48, 64), np.uint8)
    with pytest.raises(ValueError, match="goal asks for camera 'other' but the CameraInfo is "
                                         "from 'cam'"):
        goal_request(make_goal(initial, camera_frame_id="other"), inputs, CalibrationParams(), 0)
    request = goal_request(make_goal(initial, seed=7), inputs, CalibrationParams(), 0)
    assert (request.camera_frame, request.map_frame, request.seed) == ("cam", "map", 7)
    assert translation_error(request.initial, initial) < 1e-12
