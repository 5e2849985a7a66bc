"""`semcal export-pose`: each form parsed back with its tool's public convention composes to the
pose (1e-9); bad pose files are one line and exit 1; the calibrator's /tf_static, heard by another
process, agrees with the exported form of the pose it wrote."""

from __future__ import annotations

import math
import re
import shlex
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from semcal_ros.cli import main as semcal_main
from semcal_ros.export import framed_pose_from_dict, read_framed_pose
from semcal_ros.engine.pose import Pose

REPO = Path(__file__).resolve().parents[1]

#: Poses with awkward rotations: near gimbal lock, yaw past 180 deg, a typical roadside camera.
POSES = {
    "roadside": Pose.from_body_rpy_deg(np.array([12.345678901234567, -3.2, 6.1]),
                                       np.array([0.7, 11.3, -137.25])),
    "near_gimbal": Pose(np.array([-0.1, 1e-7, 250.0]),
                        Rotation.from_euler("xyz", [0.3, math.pi / 2 - 1e-6, -2.9]).as_quat()),
    "random": Pose(np.array([501.2, -77.3, 2.25]), Rotation.random(random_state=7).as_quat()),
}


def write_pose_file(path: Path, pose: Pose, parent: str = "map",
                    child: str = "camera_optical") -> Path:
    path.write_text(yaml.safe_dump({"frame_id": parent, "child_frame_id": child,
                                    "translation": [float(v) for v in pose.translation],
                                    "rotation": [float(v) for v in pose.quaternion]}))
    return path


def export(capsys, *argv: str) -> str:
    assert semcal_main(["export-pose", *argv]) == 0
    return capsys.readouterr().out


def transform(xyz, rotation: Rotation) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation.as_matrix(), xyz
    return out


def pose_matrix(pose: Pose) -> np.ndarray:
    return transform(pose.translation, Rotation.from_quat(pose.quaternion))


def urdf_rpy_value(text: str) -> list[float]:
    """URDF numbers, including the 'pi' expressions camera URDFs (xacro-expanded) carry."""
    return [float(eval(v, {"__builtins__": {}}, {"pi": math.pi})) for v in text.split()]


def compose_urdf(text: str, parent: str, child: str) -> np.ndarray:
    """Walk the fixed joints from parent to child; each origin is URDF's xyz + fixed-axis rpy
    (= scipy 'xyz' extrinsic)."""
    robot = ET.fromstring(text)
    assert robot.tag == "robot" and robot.get("name") == "semcal_calibration"
    links = {link.get("name") for link in robot.findall("link")}
    joints = {j.find("parent").get("link"): j for j in robot.findall("joint")}
    total, frame = np.eye(4), parent
    while frame != child:
        joint = joints[frame]
        assert joint.get("type") == "fixed"
        origin = joint.find("origin")
        xyz = urdf_rpy_value(origin.get("xyz"))
        rpy = urdf_rpy_value(origin.get("rpy"))
        total = total @ transform(xyz, Rotation.from_euler("xyz", rpy))
        frame = joint.find("child").get("link")
        assert frame in links
    return total


@pytest.mark.parametrize("name", sorted(POSES))
def test_urdf_composes_to_the_pose(tmp_path, capsys, name):
    pose = POSES[name]
    path = write_pose_file(tmp_path / "pose.yaml", pose)
    text = export(capsys, str(path), "--format", "urdf")
    np.testing.assert_allclose(compose_urdf(text, "map", "camera_optical"), pose_matrix(pose),
                               atol=1e-9, rtol=0)
    # full precision: the translation is written as the double itself
    origin = ET.fromstring(text).find("joint/origin").get("xyz").split()
    assert [float(v) for v in origin] == [float(v) for v in pose.translation]


@pytest.mark.parametrize("name", sorted(POSES))
def test_urdf_with_a_body_frame(tmp_path, capsys, name):
    pose = POSES[name]
    path = write_pose_file(tmp_path / "pose.yaml", pose)
    out = tmp_path / "cam.urdf"
    assert export(capsys, str(path), "--format", "urdf", "--body-frame", "camera_link",
                  "--out", str(out)) == ""
    text = out.read_text()
    robot = ET.fromstring(text)
    second = [j for j in robot.findall("joint") if j.find("parent").get("link") == "camera_link"]
    assert len(second) == 1 and [float(v) for v in second[0].find("origin").get("rpy").split()] == [
        -math.pi / 2, 0.0, -math.pi / 2]
    assert second[0].find("origin").get("xyz") == "0 0 0"
    np.testing.assert_allclose(compose_urdf(text, "map", "camera_optical"), pose_matrix(pose),
                               atol=1e-9, rtol=0)
    # camera_link is the REP-103 body: its roll, pitch, yaw are the pose's body angles
    body = compose_urdf(text, "map", "camera_link")
    yaw, pitch, roll = Rotation.from_matrix(body[:3, :3]).as_euler("ZYX")
    np.testing.assert_allclose(Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix(),
                               Rotation.from_euler("ZYX", pose.body_rpy()[::-1]).as_matrix(),
                               atol=1e-9)


def parse_static_tf(line: str) -> tuple[dict[str, float], str, str]:
    """The flags of `ros2 run tf2_ros static_transform_publisher` (Jazzy's new-style form)."""
    argv = shlex.split(line)
    assert argv[:4] == ["ros2", "run", "tf2_ros", "static_transform_publisher"]
    flags = dict(zip(argv[4::2], argv[5::2]))
    assert len(argv[4:]) == 2 * len(flags)
    assert set(flags) == {"--x", "--y", "--z", "--qx", "--qy", "--qz", "--qw", "--frame-id",
                          "--child-frame-id"}
    values = {k[2:]: float(v) for k, v in flags.items() if "frame" not in k}
    return values, flags["--frame-id"], flags["--child-frame-id"]


@pytest.mark.parametrize("name", sorted(POSES))
def test_static_tf_line_composes_to_the_pose(tmp_path, capsys, name):
    pose = POSES[name]
    path = write_pose_file(tmp_path / "pose.yaml", pose, "world", "north_optical")
    text = export(capsys, str(path), "--format", "static-tf")
    assert text.count("\n") == 1
    v, parent, child = parse_static_tf(text)
    assert (parent, child) == ("world", "north_optical")
    # static_transform_publisher publishes the child frame's pose in the parent frame
    got = transform([v["x"], v["y"], v["z"]], Rotation.from_quat([v["qx"], v["qy"], v["qz"],
                                                                   v["qw"]]))
    np.testing.assert_allclose(got, pose_matrix(pose), atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", sorted(POSES))
def test_matrix_yaml_maps_child_points_into_the_parent(tmp_path, capsys, name):
    pose = POSES[name]
    path = write_pose_file(tmp_path / "pose.yaml", pose)
    data = yaml.safe_load(export(capsys, str(path), "--format", "matrix"))
    assert "maps points given in frame <b> into frame <a>" in data["convention"]
    forward = np.array(data["T_map_camera_optical"])
    backward = np.array(data["T_camera_optical_map"])
    assert forward.shape == backward.shape == (4, 4)
    np.testing.assert_allclose(forward, pose_matrix(pose), atol=1e-9, rtol=0)
    np.testing.assert_allclose(forward @ backward, np.eye(4), atol=1e-9)
    # a point 10 m in front of the camera (optical z) lands on the viewing ray in the map
    ahead = forward @ np.array([0.0, 0.0, 10.0, 1.0])
    np.testing.assert_allclose(ahead[:3], pose.translation + 10 * pose.rotation[:, 2], atol=1e-9)
    np.testing.assert_allclose(pose.transform_points(ahead[None, :3])[0],
                               (backward @ ahead)[:3], atol=1e-9)


def test_a_result_with_its_extras_and_an_rpy_initial_pose_are_read(tmp_path):
    result = {"frame_id": "map", "child_frame_id": "camera_optical",
              "translation": [1, 2, 3], "rotation": [0, 0, 0, 1],
              "loss": 0.1, "quality": {"verdict": "good"}}
    fp = framed_pose_from_dict(result)
    assert (fp.parent, fp.child) == ("map", "camera_optical")
    initial = {"frame_id": "map", "child_frame_id": "cam", "translation": [0, 0, 5],
               "rpy_deg": [0, 10, 90]}
    np.testing.assert_allclose(framed_pose_from_dict(initial).pose.body_rpy_deg(), [0, 10, 90],
                               atol=1e-9)


@pytest.mark.parametrize("content,message", [
    ("child_frame_id: c\ntranslation: [0, 0, 0]\nrotation: [0, 0, 0, 1]\n",
     "missing field 'frame_id'"),
    ("frame_id: map\nchild_frame_id: c\nrotation: [0, 0, 0, 1]\n",
     "missing field 'translation'"),
    ("frame_id: map\nchild_frame_id: c\ntranslation: [0, 0, 0]\n", "missing field 'rotation'"),
    ("frame_id: map\nchild_frame_id: c\ntranslation: [0, 0]\nrotation: [0, 0, 0, 1]\n",
     "'translation' must be a list of 3 numbers"),
    ("frame_id: map\nchild_frame_id: c\ntranslation: [0, 0, 0]\nrotation: [0, 0, 1]\n",
     "'rotation' must be a list of 4 numbers"),
    ("frame_id: map\nchild_frame_id: c\ntranslation: [0, 0, 0]\nrotation: [0, 0, 0, 0]\n",
     "'rotation' is a zero quaternion"),
    ("frame_id: map\nchild_frame_id: c\ntranslation: [0, 0, 0]\nrotation: [0, .nan, 0, 1]\n",
     "'rotation' contains NaN"),
    ("frame_id: map\nchild_frame_id: c\ntranslation: [0, 0, 0]\nrotation: [0, 0, 0, 2]\n",
     "not a unit quaternion"),
    ("frame_id: map\nchild_frame_id: map\ntranslation: [0, 0, 0]\nrotation: [0, 0, 0, 1]\n",
     "frame_id and child_frame_id are both 'map'"),
    ("[1, 2, 3]\n", "expected a YAML mapping"),
    ("frame_id: [unclosed\n", "invalid YAML"),
])
def test_bad_pose_files_are_one_line_and_exit_1(tmp_path, content, message):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    proc = subprocess.run([sys.executable, "-m", "semcal_ros.cli", "export-pose", str(path),
                           "--format", "urdf"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("semcal export-pose: error: ") and message in lines[0], lines[0]


def test_missing_file_and_body_frame_misuse_are_one_line(tmp_path, capsys):
    assert semcal_main(["export-pose", str(tmp_path / "none.yaml"), "--format", "matrix"]) == 1
    assert "pose file not found" in capsys.readouterr().err
    path = write_pose_file(tmp_path / "pose.yaml", POSES["roadside"])
    assert semcal_main(["export-pose", str(path), "--format", "static-tf",
                        "--body-frame", "camera_link"]) == 1
    assert "--body-frame applies to --format urdf only" in capsys.readouterr().err
    assert semcal_main(["export-pose", str(path), "--format", "urdf",
                        "--body-frame", "camera_optical"]) == 1
    assert "must differ from the pose's frames" in capsys.readouterr().err


def test_read_framed_pose_of_a_written_result(tmp_path):
    from semcal_ros.io.files import write_pose

    pose = POSES["random"]
    write_pose(tmp_path / "result.yaml", pose, {"loss": 0.2})
    fp = read_framed_pose(tmp_path / "result.yaml")
    np.testing.assert_allclose(fp.pose.translation, pose.translation, atol=0)
    np.testing.assert_allclose(fp.pose.quaternion, pose.quaternion, atol=1e-15)


# --- the calibrator's /tf_static, heard by another process -----------------------------------
#: tf2_ros is not on PyPI (docs/ros.md); this listener does what a tf2 static listener does: a
#: reliable, transient-local subscription to /tf_static (depth 100), in a process of its own.
TF_LISTENER = r'''
import sys, time, rclpy, yaml
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage
child = sys.argv[1]
rclpy.init()
node = rclpy.create_node("tf_static_listener")
got = []
qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
node.create_subscription(TFMessage, "/tf_static", lambda m: got.extend(m.transforms), qos)
deadline = time.monotonic() + 60
while not any(t.child_frame_id == child for t in got) and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
tf = [t for t in got if t.child_frame_id == child][-1]
tr, q = tf.transform.translation, tf.transform.rotation
print("TF " + yaml.safe_dump({"frame_id": tf.header.frame_id, "child_frame_id": child,
                             "translation": [tr.x, tr.y, tr.z], "rotation": [q.x, q.y, q.z, q.w]},
                            default_flow_style=True, width=10000).strip())
'''


@pytest.mark.slow
@pytest.mark.ros
def test_tf_static_of_the_calibrator_matches_the_exported_yaml(tmp_path, demo_scene):
    rclpy = pytest.importorskip("rclpy")
    from sensor_msgs.msg import CameraInfo, Image

    from semcal_ros.io.files import pose_to_dict, read_pose
    from semcal_ros.ros import conversions as conv
    from semcal_ros.ros import qos
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal

    from ros_helpers import RosGraph, spin_until
    from test_ros_calibrator import CHEAP_ENGINE, camera_messages

    graph = RosGraph(tmp_path / "logs")
    ctx = graph.context()
    node = rclpy.create_node("export_pose_test", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        graph.start_node("calibrator", params={"map_file": str(demo_scene / "map.ply"),
                                               **CHEAP_ENGINE})
        watcher = DiagnosticsWatcher(node)
        msgs = camera_messages(demo_scene)
        pubs = {t: node.create_publisher(CameraInfo if "info" in t else Image, t,
                                         qos.reliable(1)) for t in msgs}
        node.create_timer(0.3, lambda: [pubs[t].publish(m) for t, m in msgs.items()])
        spin_until(executor, lambda: watcher.get("calibrator").get("message") == "ready", 90,
                   "the calibrator to hold a map, a label image and CameraInfo")
        client = CalibrateClient(node)
        client.wait_for_server(30)
        out = client.call(executor, make_goal(read_pose(demo_scene / "initial.yaml")),
                          timeout=180)
        assert out.status == "succeeded", out.result.message
        tf = out.result.transform
        # the pose YAML an operator writes from the result, and its exported forms
        result_yaml = tmp_path / "result.yaml"
        result_yaml.write_text(yaml.safe_dump(pose_to_dict(
            conv.pose_from_transform(tf), frame_id=tf.header.frame_id,
            child_frame_id=tf.child_frame_id)))
        listener = graph.start("tf_listener", "python", "-c", TF_LISTENER, tf.child_frame_id)
        assert listener.wait(90) == 0, listener.log()
    finally:
        executor.shutdown()
        node.destroy_node()
        graph.close()
        print(graph.logs())
    heard = yaml.safe_load(re.search(r"^TF (.*)$", listener.log(), re.M).group(1))
    assert (heard["frame_id"], heard["child_frame_id"]) == ("map", "camera_optical")
    heard_matrix = transform(heard["translation"], Rotation.from_quat(heard["rotation"]))

    def cli(fmt: str) -> str:
        proc = subprocess.run([sys.executable, "-m", "semcal_ros.cli", "export-pose",
                               str(result_yaml), "--format", fmt], capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        return proc.stdout

    v, parent, child = parse_static_tf(cli("static-tf"))
    assert (parent, child) == ("map", "camera_optical")
    line = transform([v["x"], v["y"], v["z"]],
                     Rotation.from_quat([v["qx"], v["qy"], v["qz"], v["qw"]]))
    np.testing.assert_allclose(line, heard_matrix, atol=1e-9, rtol=0)
    matrix = yaml.safe_load(cli("matrix"))
    np.testing.assert_allclose(np.array(matrix["T_map_camera_optical"]), heard_matrix,
                               atol=1e-9, rtol=0)
    np.testing.assert_allclose(compose_urdf(cli("urdf"), "map", "camera_optical"),
                               heard_matrix, atol=1e-9, rtol=0)
