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

from ros_helpers import RosGraph, RosProcess, held_goal, spin_until  # noqa: E402

pytestmark = pytest.mark.ros

#: A cheap engine schedule (~80 evaluations, about 3 s on the demo map): these tests are about
#: the node, not the optimum. How far 80 evaluations get from 1.12 m off differs between CPUs
#: (about 0.3 m on one, 1.10 m on two AMD EPYCs; why is not known), so a good goal is judged
#: against the offline engine run on the same inputs with the same settings
#: (:func:`offline_calibration`), never against how far a short search got.
CHEAP_ENGINE = {"engine.schedule.max_evaluations": [40, 20, 20],
                "engine.schedule.restarts": [0, 0, 0], "engine.verification.starts": 0,
                "engine.quality.evidence_evaluations": 15}


def offline_calibration(scene: Path, engine: dict[str, Any], initial: Any = None,
                        camera: Path | None = None) -> Any:
    """What the calibrator node must answer for a goal from ``initial`` (default: the scene's
    initial.yaml) on ``scene``'s map and the label image and CameraInfo in ``camera`` (default:
    ``scene``) with the node's parameter overrides ``engine``: the engine called as the node
    calls it (the whole map prepared once, the node's default seed 0), in this process."""
    from semcal_ros.engine.calibration import calibrate_and_draw
    from semcal_ros.engine.config import apply_flat
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.render import prepare_map
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply

    params = apply_flat(CalibrationParams(), {k[len("engine."):]: v for k, v in engine.items()})
    mapping = LabelMapping()
    prepared = prepare_map(read_ply(scene / "map.ply"), mapping)
    camera = camera or scene
    return calibrate_and_draw(None, read_label_image(camera / "labels.png"),
                              read_camera_info(camera / "camera_info.yaml"),
                              initial or read_pose(camera / "initial.yaml"), params, mapping,
                              prepared=prepared, draw=False, seed=0).result


def assert_same_pose(pose: Any, expected: Any, what: str) -> None:
    """The node's pose is the offline engine's (same inputs, same settings, same arithmetic:
    equal up to the float rounding of the messages)."""
    from semcal_ros.engine.pose import rotation_error_deg, translation_error

    dt, dr = translation_error(pose, expected), rotation_error_deg(pose, expected)
    assert dt < 1e-6 and dr < 1e-6, f"{what}: {dt * 100:.4f} cm / {dr:.6f} deg from the " \
                                    "offline engine's result"


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
    map_points: str
    expected: Any  # the offline engine's result for a good goal (:func:`offline_calibration`)

    def diag(self) -> dict[str, str]:
        return self.watcher.get("calibrator")

    def call(self, goal: Any, timeout: float = 120.0) -> Any:
        return self.client.call(self.executor, goal, timeout=timeout)

    def start(self) -> Any:
        from semcal_ros.io.files import read_pose

        return read_pose(self.scene / "initial.yaml")

    def good_goal(self, **options: Any) -> Any:
        from semcal_ros.ros.client import make_goal

        return make_goal(self.start(), **options)


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
        client.wait_for_server(30)
        yield Calibrator(graph, proc, node, executor, client, watcher, demo_scene, msgs,
                         watcher.get("calibrator")["map_points"],
                         offline_calibration(demo_scene, CHEAP_ENGINE))
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


def assert_succeeded(out: Any, scene: Path, expected: Any) -> None:
    from semcal_ros.engine.evidence import STRIPS
    from semcal_ros.io.files import read_pose
    from semcal_ros.engine.pose import translation_error

    assert out.accepted and out.status == "succeeded", (out.status, out.result)
    r = out.result
    assert r.success is True
    assert r.message.startswith("calibrated 'camera_optical': t = ["), r.message
    assert f"loss {r.loss:.5f}" in r.message and "1/1 runs agree" in r.message
    assert (r.transform.header.frame_id, r.transform.child_frame_id) == ("map", "camera_optical")
    pose = conv.pose_from_transform(r.transform)
    # the node answers what the engine finds for the same inputs and settings, and the search
    # did not end where it started
    assert_same_pose(pose, expected.pose, "the node's result")
    assert translation_error(pose, read_pose(scene / "initial.yaml")) > 0.01
    assert r.loss == pytest.approx(expected.loss, rel=1e-9, abs=1e-12)
    assert r.verdict == expected.quality.verdict, (r.verdict, r.verdict_reason)
    q = expected.quality  # and the same report
    assert r.agreement == pytest.approx(q.agreement, abs=1e-9)
    ut = r.uncertainty_translation_m
    assert (ut.x, ut.y, ut.z) == pytest.approx(q.uncertainty_translation_m, abs=1e-9)
    assert abs(np.linalg.norm(pose.quaternion) - 1.0) < 1e-6
    assert 0.0 < r.loss < 1.0 and math.isfinite(r.loss)
    # the search's renders plus the evidence's (each image strip left out in turn) and the report
    assert 0 < r.evaluations <= sum(CHEAP_ENGINE["engine.schedule.max_evaluations"]) + 10 + \
        STRIPS * CHEAP_ENGINE["engine.quality.evidence_evaluations"] + 1
    assert_quality(r)
    assert r.seconds > 0.0
    assert (r.spread_translation_m, r.spread_rotation_deg) == (0.0, 0.0)  # one run


def assert_quality(r: Any) -> None:
    """A success carries its quality report: a verdict with its reason and the figures."""
    from semcal_ros.engine.quality import VERDICTS

    assert r.verdict in VERDICTS and r.verdict_reason, (r.verdict, r.verdict_reason)
    assert f"verdict {r.verdict}" in r.message
    assert 0.0 < r.agreement <= 1.0 and 0.0 < r.coverage <= 1.0
    assert len(r.agreement_classes) == len(r.agreement_per_class) > 0
    assert "road" in r.agreement_classes
    assert all(0.0 <= v <= 1.0 for v in r.agreement_per_class)
    ut, ur = r.uncertainty_translation_m, r.uncertainty_rpy_deg
    assert all(0.0 <= v <= 2.5 for v in (ut.x, ut.y, ut.z)), ut  # capped at the search bounds
    assert all(0.0 <= v <= 5.0 for v in (ur.y, ur.z)), ur
    assert max(ut.x, ut.y, ut.z) > 0.0, ut  # measured, not left at zero


def wait_idle(c: Calibrator, timeout: float = 30.0) -> None:
    """Until a diagnostics message sent from now on says the node is idle (the one held may
    predate the goal)."""
    c.watcher.latest.pop("calibrator", None)
    spin_until(c.executor, lambda: c.diag().get("state") == "idle", timeout, "the engine to stop")


@pytest.mark.slow
def test_goal_sequences_on_one_calibrator_lose_no_result(calibrator):
    """abort -> succeed -> abort -> cancel -> succeed -> abort on one process: each result whole
    (rclpy once turned every result after the first of another severity into an empty one)."""
    c = calibrator
    frame_problem = c.good_goal(map_frame="odom")
    bad_quaternion = c.good_goal()
    bad_quaternion.initial_pose.pose.orientation.w = 2.0

    assert_aborted(c.call(frame_problem), "invalid goal",
                   "initial_pose is in frame 'odom' but the map is in 'map'")
    assert_succeeded(c.call(c.good_goal()), c.scene, c.expected)
    assert_aborted(c.call(bad_quaternion), "invalid goal", "not a unit quaternion")

    running = c.client.send(c.executor, held_goal(c.start()))  # runs until cancelled
    assert running.accepted
    c.client.cancel(c.executor, running)
    assert_cancelled(c.client.wait(c.executor, running, timeout=30))
    wait_idle(c)  # a cancel is answered at once; the engine stops at its next check

    assert_succeeded(c.call(c.good_goal()), c.scene, c.expected)
    assert_aborted(c.call(frame_problem), "initial_pose is in frame 'odom'")
    assert c.proc.running()
    assert "Error raised in execute callback" not in c.proc.log()


# --- bad inputs: each refused with one message naming it, and what the node holds is kept -----
def _goal_case(change):
    def run(c: Calibrator, expected: str) -> str:
        goal = c.good_goal()
        change(goal)
        out = c.call(goal, timeout=30)
        assert_aborted(out)
        return out.result.message
    return run


def _set(path: str, value: Any):
    def change(goal: Any) -> None:
        *parents, last = path.split(".")
        obj = goal
        for name in parents:
            obj = getattr(obj, name)
        setattr(obj, last, value)
    return change


def _message_case(topic: str, make: Any, key: str):
    """Publish a bad message until the calibrator's diagnostics show it refused."""
    def run(c: Calibrator, expected: str) -> str:
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2

        kind = {"/map": PointCloud2, "/camera/camera_info": CameraInfo}.get(topic, Image)
        profile = qos.latched() if topic == "/map" else qos.reliable(1)
        pub = c.node.create_publisher(kind, topic, profile)
        try:
            msg = make(c)
            deadline = time.monotonic() + 20
            while expected not in c.diag().get(f"input_error.{key}", ""):
                if time.monotonic() > deadline:
                    break
                pub.publish(msg)
                end = time.monotonic() + 0.3
                while time.monotonic() < end:
                    c.executor.spin_once(timeout_sec=0.05)
            return c.diag().get(f"input_error.{key}", f"(no refusal of {topic}: {c.diag()})")
        finally:
            c.node.destroy_publisher(pub)
    return run


def _cloud(c: Calibrator, xyz: np.ndarray) -> Any:
    from semcal_ros.engine.cloud import LabelledCloud

    cloud = LabelledCloud(np.asarray(xyz, float), np.full(len(xyz), 50, np.uint16))
    return conv.cloud_to_pointcloud2(cloud, conv.make_header("map", 1.0), extra_fields=False)


def _camera_info(c: Calibrator, **k_entries: float) -> Any:
    msg = c.camera_msgs["/camera/camera_info"]
    out = type(msg)()
    out.header, out.width, out.height = msg.header, msg.width, msg.height
    out.distortion_model, out.d, out.r, out.p = msg.distortion_model, msg.d, msg.r, msg.p
    k = np.array(msg.k, float)
    for index, value in k_entries.items():
        k[int(index[1:])] = value
    out.k = k
    return out


CALIBRATOR_CASES = [
    ("goal-translation-bound-1e9", _goal_case(_set("bound_translation_m.x", 1e9)),
     "bound_translation_m.x 1e+09 m is beyond what the search can cover (at most 50 m)"),
    ("goal-rpy-bound-1e9", _goal_case(_set("bound_rpy_deg.z", 1e9)),
     "bound_rpy_deg.z 1e+09 deg is beyond what the search can cover (at most 180 deg)"),
    ("goal-negative-bound", _goal_case(_set("bound_rpy_deg.y", -1.0)),
     "bound_rpy_deg.y must be >= 0 (0 = node default), got -1.0"),
    ("goal-nan-bound", _goal_case(_set("bound_translation_m.z", float("nan"))),
     "bound_translation_m.z must be >= 0"),
    ("goal-nan-position", _goal_case(_set("initial_pose.pose.position.x", float("nan"))),
     "initial_pose contains NaN or infinite values"),
    ("goal-infinite-orientation", _goal_case(_set("initial_pose.pose.orientation.x",
                                                  float("inf"))),
     "initial_pose contains NaN or infinite values"),
    ("goal-zero-quaternion", _goal_case(lambda g: (_set("initial_pose.pose.orientation.w", 0.0)(g),
                                                   _set("initial_pose.pose.orientation.x", 0.0)(g),
                                                   _set("initial_pose.pose.orientation.y", 0.0)(g),
                                                   _set("initial_pose.pose.orientation.z", 0.0)(g))),
     "not a unit quaternion (norm 0)"),
    ("goal-pose-in-odom", _goal_case(_set("initial_pose.header.frame_id", "odom")),
     "initial_pose is in frame 'odom' but the map is in 'map'"),
    ("goal-pose-100-km-away", _goal_case(_set("initial_pose.pose.position.x", 1e5)),
     "km from the map (map spans x "),
    ("goal-other-camera", _goal_case(_set("camera_frame_id", "rear_camera")),
     "goal asks for camera 'rear_camera' but the CameraInfo is from 'camera_optical'"),
    ("goal-unknown-loss", _goal_case(_set("loss", "l1")), "loss must be 'l2', 'huber'"),
    ("goal-bad-roll", _goal_case(_set("roll", 7)), "roll must be ROLL_DEFAULT"),
    ("goal-bad-yaw-search", _goal_case(_set("yaw_search", 9)), "yaw_search must be 0-2"),
    ("goal-negative-verification", _goal_case(_set("verification_starts", -5)),
     "verification_starts must be >= 0 (-1 = node default), got -5"),
    ("map-empty", _message_case("/map", lambda c: _cloud(c, np.zeros((0, 3))), "map"),
     "the map message is empty; keeping the map held ("),
    ("map-all-nan", _message_case("/map", lambda c: _cloud(c, np.full((500, 3), np.nan)), "map"),
     "has no finite point (500 points, all NaN or infinite); keeping the map held"),
    ("camera-info-nan-fx", _message_case("/camera/camera_info",
                                         lambda c: _camera_info(c, k0=float("nan")),
                                         "CameraInfo"),
     "K contains NaN or infinite values"),
    ("camera-info-k-zeros", _message_case(
        "/camera/camera_info", lambda c: _camera_info(c, **{f"k{i}": 0.0 for i in range(9)}),
        "CameraInfo"), "K is all zeros (camera not calibrated)"),
    ("camera-info-negative-fy", _message_case("/camera/camera_info",
                                              lambda c: _camera_info(c, k4=-480.0),
                                              "CameraInfo"),
     "focal lengths must be positive"),
    ("labels-rgb-encoding", _message_case(
        "/camera/labels", lambda c: c.camera_msgs["/camera/image_raw"], "label image"),
     "expected a mono8 label image, got encoding 'rgb8'"),
    ("camera-image-mono", _message_case(
        "/camera/image_raw", lambda c: c.camera_msgs["/camera/labels"], "camera image"),
     "expected an rgb8 or bgr8 image, got encoding 'mono8'"),
]


@pytest.mark.parametrize("case,expected", [c[1:] for c in CALIBRATOR_CASES],
                         ids=[c[0] for c in CALIBRATOR_CASES])
def test_calibrator_refuses_bad_input(calibrator, case, expected):
    message = case(calibrator, expected)
    assert expected in message, message
    assert "\n" not in message and "Traceback" not in calibrator.proc.log()
    assert calibrator.proc.running()


def test_calibrator_kept_its_inputs_and_serves_a_good_goal_after_the_bad_inputs(calibrator):
    """After a refusal of each input (no good message re-sent since), the node still holds the
    map, the label image and CameraInfo it had, and calibrates. The refusals are sent here, so
    the test holds alone and in any order beside the table above."""
    c = calibrator
    for name in ("map-empty", "camera-info-nan-fx", "labels-rgb-encoding"):
        _, case, expected = next(case for case in CALIBRATOR_CASES if case[0] == name)
        message = case(c, expected)
        assert expected in message, message
    d = c.diag()
    assert d["map_points"] == c.map_points != "0"
    assert d["camera_info"] == "960x600 'camera_optical'"
    assert d["label_image"] == "960x600"
    assert "CameraInfo: CameraInfo" not in c.proc.log()  # the prefix once, not twice
    assert "ignoring CameraInfo: K contains NaN or infinite values" in c.proc.log()
    assert_succeeded(c.call(c.good_goal()), c.scene, c.expected)


def test_a_goal_while_one_runs_is_answered_with_the_reason(calibrator):
    c = calibrator
    first = c.client.send(c.executor, held_goal(c.start()))  # runs until cancelled below
    assert first.accepted
    # this goal, by its id: a diagnostics message from the goal before it also said "running",
    # and an accepted goal is claimed only once its execute callback runs (under load, after
    # the next goal had arrived: that one then ran, and this one was the busy one)
    first_id = bytes(first.goal_handle.goal_id.uuid).hex()[:8]
    spin_until(c.executor, lambda: c.diag().get("state", "").startswith(f"running {first_id}"),
               30, f"the first goal ({first_id}) to run")
    second = c.call(c.good_goal(), timeout=30)
    assert_aborted(second, "busy: goal ", "has been running for", "(one calibration at a time)")
    spin_until(c.executor, lambda: c.diag()["last_rejection"].startswith("busy: goal "), 30,
               "the busy note in the diagnostics")
    c.client.cancel(c.executor, first)
    assert_cancelled(c.client.wait(c.executor, first, timeout=60))
    wait_idle(c)
    third = c.call(c.good_goal(map_frame="odom"))  # the next goal clears the busy note
    assert_aborted(third, "frame 'odom'")
    spin_until(c.executor, lambda: c.diag().get("last_rejection") == "none", 30,
               "last_rejection to be cleared")
    assert_succeeded(c.call(c.good_goal()), c.scene, c.expected)  # and the node calibrates again


def test_a_degenerate_best_pose_is_never_published(calibrator):
    """50 m above the map's top, looking straight up, every yaw of the yaw search and every pose
    within its bounds sees sky: the best pose is degenerate (once published at t = -2.26e8 m with
    loss 10); it must come back as a failure. (From the camera's own height, looking up, the
    bounded search finds rooftops at 5 % coverage: a poor result, not a degenerate one.)"""
    from geometry_msgs.msg import TransformStamped

    from semcal_ros.io.files import read_pose
    from semcal_ros.engine.pose import Pose, translation_error
    from semcal_ros.ros.client import make_goal

    c = calibrator
    published: list[Any] = []
    sub = c.node.create_subscription(TransformStamped, "/calibration/transform",
                                     published.append, qos.latched())
    try:
        start = c.start()
        above = start.translation + np.array([0.0, 0.0, 80.0])  # the map's top is < 30 m
        up = Pose.from_body_rpy_deg(above, [0.0, -89.0, 0.0])
        out = c.call(make_goal(up, yaw_search=2), timeout=120)
        assert out.status == "aborted" and out.result.success is False, out.result
        message = out.result.message
        assert message.startswith("calibration failed: ") and "loss 10" in message, message
        assert message.count("calibration failed") == 1, message
        assert_empty_transform(out.result)
        # A good goal afterwards: its transform is the last one published, and the stream is in
        # order, so anything the failed goal had published would have arrived before it. Every
        # transform received (the latched one of an earlier goal, if any, then this one) is a
        # calibration of the camera near the ground, none from 80 m up.
        good = c.call(c.good_goal())
        assert_succeeded(good, c.scene, c.expected)
        spin_until(c.executor, lambda: published and published[-1].transform
                   == good.result.transform.transform, 30, "the good goal's transform")
        truth = read_pose(c.scene / "ground_truth.yaml")
        for msg in published:
            assert translation_error(conv.pose_from_transform(msg), truth) < 5.0, msg
    finally:
        c.node.destroy_subscription(sub)
