"""``calibration_monitor``: the drift watch of one camera or several on one map (docs/drift.md).

Every ``period`` seconds, per camera, the newest label image is checked against the camera's
current calibration (:class:`semcal_ros.engine.drift.DriftChecker`: the loss at the calibration against
a small coarse search around it). The result goes to ``/diagnostics`` (one status per camera:
OK, WARN or ERROR with the estimated drift in cm and deg) and, latched, to
``calibration/drift`` (``<name>/calibration/drift`` for a named camera;
semcal_interfaces/msg/CalibrationDrift). A check that cannot judge (no label image or
calibration yet, the map covers too little of the image) is a WARN whose message says so.

Inputs, as the calibrator's (:mod:`semcal_ros.ros.camera_inputs`): ``camera/labels`` and
``camera/camera_info`` for the single unnamed camera, ``<name>/labels`` ... with
``cameras: [north, ...]``; the map from ``map_file`` or the latched ``map`` topic, prepared once
(:mod:`semcal_ros.ros.held_map`). The calibration of a camera (its optical frame in the map
frame) comes from ``/tf_static``, ``calibration/transform`` or the ``calibration_file`` pose YAML
(``{name}`` in the path stands for the camera's name); the newest wins.

The reference (the first check after a calibration, if it found no drift) and the confirmation
(a level is raised after ``confirm`` checks in a row agree on it) are the engine's
:class:`~semcal_ros.engine.drift_watch.DriftWatch`, one per camera; the texts of the drift
message and the diagnostics are :mod:`semcal_ros.ros.monitor_status`'s. The node is wiring.

With ``auto_recalibrate`` an ERROR sends one goal to the ``calibrate`` action (from the estimated
pose); the monitor never replaces a transform itself: the calibrator publishes the result only if
its verdict is one of its ``publish_verdicts`` (a failed one never, by default), and the monitor
logs how the goal ended. Bad input is refused in one line and the
node keeps what it held.
"""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from semcal_interfaces.msg import CalibrationDrift
from semcal_ros.engine.drift import DriftChecker, DriftParams, DriftReport, check_params, unknown
from semcal_ros.engine.drift_watch import DriftWatch, Verdict
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import mapping_for
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.calibration_intake import CalibrationIntake
from semcal_ros.ros.camera_inputs import CameraInputs, camera_topics
from semcal_ros.ros.diagnostics import Diagnostics, Report
from semcal_ros.ros.held_map import EMPTY_CLOUD
from semcal_ros.ros.map_intake import MapIntake
from semcal_ros.ros.monitor_status import camera_report, drift_message, node_report
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import run_node

try:  # not on PyPI: .ci/setup.d/10-interfaces.sh builds it where it is missing
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None


@dataclass
class MonitorParams:
    """The node's own parameters; ``engine.*`` (the loss) and ``drift.*`` (the check) beside."""

    map_file: str = ""  # labelled PLY loaded at start; a map on the topic replaces it
    map_frame: str = "map"
    label_mapping: str = ""  # YAML of the label alignment (as the calibrator's)
    cameras: tuple[str, ...] = ()  # names (topics <name>/labels ...); empty: camera/...
    calibration_file: str = ""  # pose YAML of the calibration ({name}: the camera's name)
    period: float = 10.0  # s between checks of each camera
    confirm: int = 2  # checks in a row that must agree before a level is raised
    auto_recalibrate: bool = False  # an ERROR sends a goal to the calibrate action
    calibrate_action: str = "calibrate"
    diagnostics_period: float = 1.0
    # a static camera: each check judges the per-pixel fusion of the last N label images the
    # checks took (one per period; DriftWatch.windowed), as the calibrator's label_window
    label_window: int = 1

    def __post_init__(self) -> None:
        if not self.period > 0:
            raise ValueError(f"period must be > 0 s, got {self.period}")
        if self.label_window < 1:
            raise ValueError(f"label_window must be >= 1 frames, got {self.label_window}")
        if self.confirm < 1:
            raise ValueError(f"confirm must be >= 1, got {self.confirm}")
        camera_topics(self.cameras)  # raises naming a bad or repeated name


@dataclass
class _Camera:
    """What the monitor holds about one camera."""

    inputs: CameraInputs
    watch: DriftWatch
    calibrated: Pose | None = None
    calibration_source: str = "none"
    recalibrating: bool = False


class CalibrationMonitorNode(Node):
    def __init__(self) -> None:
        super().__init__("calibration_monitor")
        self.opts = declare_and_read(self, MonitorParams())
        self.engine = declare_and_read(self, CalibrationParams(), prefix="engine.")
        self.drift = declare_and_read(self, DriftParams(), prefix="drift.")
        user = LabelMapping.from_yaml(self.opts.label_mapping) if self.opts.label_mapping \
            else None
        self._lock = threading.Lock()
        self.cameras = {t.name: _Camera(CameraInputs(t, self.get_logger().error,
                                                     self.resolve_topic_name),
                                        DriftWatch(self.opts.confirm,
                                                   window=self.opts.label_window))
                        for t in camera_topics(self.opts.cameras)}
        self.maps = MapIntake(mapping_for(check_params(self.engine, self.drift), user),
                              self.opts.map_frame, self.get_logger(), on_new=self._new_map)
        if self.opts.map_file:
            self.maps.load_file(self.opts.map_file)
        self.calibrations = CalibrationIntake({n: c.inputs for n, c in self.cameras.items()},
                                              lambda: self.maps.frame, self._set_calibration,
                                              self.get_logger())
        if self.opts.calibration_file:
            self.calibrations.load_files(self.opts.calibration_file)

        inputs = MutuallyExclusiveCallbackGroup()
        checks = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, "map", self.maps.on_message, qos.latched(),
                                 callback_group=inputs)
        for cam in self.cameras.values():
            cam.inputs.subscribe(self, inputs)
        self.create_subscription(TransformStamped, "calibration/transform",
                                 self.calibrations.on_transform, qos.latched(),
                                 callback_group=inputs)
        if TFMessage is not None:
            self.create_subscription(TFMessage, "/tf_static", self.calibrations.on_tf_static,
                                     qos.latched(), callback_group=inputs)
        self.drift_pubs = {
            name: self.create_publisher(
                CalibrationDrift, f"{name}/calibration/drift" if name else "calibration/drift",
                qos.latched())
            for name in self.cameras}
        self.client = None
        if self.opts.auto_recalibrate:
            from rclpy.action import ActionClient

            from semcal_interfaces.action import Calibrate

            self.client = ActionClient(self, Calibrate, self.opts.calibrate_action,
                                       callback_group=inputs)
        self.timer = self.create_timer(self.opts.period, self.check_all, callback_group=checks)
        named = "" not in self.cameras
        self.diagnostics = Diagnostics(self, self._report, self.opts.diagnostics_period,
                                       callback_group=inputs,
                                       parts=self._camera_reports if named else None)
        labels = ", ".join(f"'{self.resolve_topic_name(c.inputs.topics.labels)}'"
                           for c in self.cameras.values())
        self.get_logger().info(f"ready: checking {labels} every {self.opts.period:g} s")

    # --- inputs -----------------------------------------------------------------------------
    def _new_map(self, _held: Any) -> None:
        with self._lock:
            for cam in self.cameras.values():  # a new map: new references
                cam.watch.new_map()

    def _set_calibration(self, name: str, pose: Pose, source: str) -> None:
        cam = self.cameras[name]
        with self._lock:
            if cam.calibrated is not None and \
                    np.allclose(cam.calibrated.vector(), pose.vector(), atol=1e-9):
                return
            cam.calibrated, cam.calibration_source, cam.recalibrating = pose, source, False
            cam.watch.new_calibration()
        self.get_logger().info(f"calibration of {cam.inputs.topics.label} from {source}")

    # --- the checks ---------------------------------------------------------------------------
    def check_all(self) -> None:
        self.calibrations.match_pending()
        for cam in self.cameras.values():
            try:
                self.check(cam)
            except Exception as exc:  # a check must never take the node down
                self.get_logger().error(f"check of {cam.inputs.topics.label} failed: {exc}")

    def check(self, cam: _Camera) -> DriftReport:
        """One check of ``cam`` (outside the lock: it is the expensive part), then its verdict
        from the camera's watch, published."""
        snap = cam.inputs.snapshot()
        held = self.maps.held
        with self._lock:
            pose, reference, epoch = cam.calibrated, cam.watch.reference, cam.watch.epoch
            labels = cam.watch.windowed(snap.labels)  # label_window > 1: the window's fusion
        if held is None:
            report = unknown(pose, "no map yet")
        elif pose is None:
            report = unknown(pose, "no calibration yet (/tf_static, calibration/transform or "
                                   "calibration_file)")
        elif snap.camera is None:
            report = unknown(pose, "no CameraInfo yet")
        else:
            checker = DriftChecker(EMPTY_CLOUD, snap.camera, pose, self.engine, self.drift,
                                   prepared=held.prepared)
            report = checker.check(labels, reference=reference)
        with self._lock:
            verdict = cam.watch.observe(report, epoch)
        self._publish(cam, verdict, snap.labels_frame or snap.frame_id)
        return verdict.report

    def _publish(self, cam: _Camera, verdict: Verdict, frame_id: str) -> None:
        msg = drift_message(verdict, frame_id or cam.inputs.name,
                            conv.make_header(self.maps.frame))
        self.drift_pubs[cam.inputs.name].publish(msg)
        if verdict.raised:
            self.get_logger().warning(f"{cam.inputs.topics.label}: {verdict.shown.upper()}: "
                                      f"{verdict.report.message}")
        if verdict.shown == "error" and self.client is not None and not cam.recalibrating:
            self._recalibrate(cam, verdict.report, frame_id)

    def _recalibrate(self, cam: _Camera, report: DriftReport, frame_id: str) -> None:
        from semcal_ros.ros.client import make_goal

        if not self.client.server_is_ready():
            self.get_logger().error(f"auto_recalibrate: action '{self.opts.calibrate_action}' "
                                    "is not available")
            return
        cam.recalibrating = True
        start = report.estimated or report.calibrated
        goal = make_goal(start, self.maps.frame, cam.inputs.name or frame_id)
        sent = self.client.send_goal_async(goal)
        sent.add_done_callback(lambda future: self._goal_sent(cam, future))
        self.get_logger().warning(f"auto_recalibrate: goal sent for {cam.inputs.topics.label} "
                                  "(the calibrator publishes the new transform if its verdict "
                                  "is one it publishes)")

    def _goal_sent(self, cam: _Camera, future: Any) -> None:
        handle = future.result()
        if handle is None or not handle.accepted:
            self.get_logger().error(f"auto_recalibrate: the goal for {cam.inputs.topics.label} "
                                    "was rejected")
            return
        handle.get_result_async().add_done_callback(lambda f: self._goal_done(cam, f))

    def _goal_done(self, cam: _Camera, future: Any) -> None:
        """Say how the recalibration ended. The calibrator decides whether its result replaces
        the transform (its ``publish_verdicts``: a failed result never does); until a new
        calibration arrives no further goal is sent for this camera (a failing recalibration
        would otherwise be repeated every period)."""
        answer = future.result()
        result = answer.result if answer is not None else None
        label = cam.inputs.topics.label
        if result is None or not result.success:
            why = result.message if result is not None else "no result"
            self.get_logger().error(f"auto_recalibrate: {label}: the goal failed ({why}); the "
                                    "calibration stays, no new goal until a new calibration "
                                    "arrives")
        elif result.verdict == "failed" or "not published" in result.message:
            self.get_logger().warning(f"auto_recalibrate: {label}: the result's verdict is "
                                      f"{result.verdict or 'none'}: {result.message}")
        else:
            self.get_logger().info(f"auto_recalibrate: {label}: {result.message}")

    # --- diagnostics --------------------------------------------------------------------------
    def _camera_reports(self) -> dict[str, Report]:
        with self._lock:
            return {name: camera_report(cam.watch, cam.calibration_source, cam.inputs)
                    for name, cam in self.cameras.items()}

    def _report(self) -> Report:
        held = self.maps.held
        values: dict[str, Any] = {"map_points": held.points if held is not None else 0,
                                  "period": self.opts.period}
        if self.maps.refusal:
            values["input_error.map"] = self.maps.refusal
        return node_report(values, self._camera_reports())


def main(args: list[str] | None = None) -> int:
    return run_node(CalibrationMonitorNode, threads=3, args=args)


if __name__ == "__main__":
    sys.exit(main())
