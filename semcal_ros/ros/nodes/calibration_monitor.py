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

The first check after a calibration arrives is its reference: a coarse search never ends exactly
at a full-resolution calibration, and later checks count drift from where it ended then. The
reference is taken only if that first check, judged alone, found no drift; otherwise checks
stay absolute. A level is raised after ``confirm`` checks in a row agree on it.

With ``auto_recalibrate`` an ERROR sends one goal to the ``calibrate`` action (from the estimated
pose); the monitor never replaces a transform itself. Bad input is refused in one line and the
node keeps what it held.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from semcal_interfaces.msg import CalibrationDrift
from semcal_ros.engine.drift import DriftChecker, DriftParams, DriftReport
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.camera_inputs import CameraInputs, camera_topics
from semcal_ros.ros.diagnostics import Diagnostics, Level, Report
from semcal_ros.ros.held_map import EMPTY_CLOUD, HeldMap
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import run_node

try:  # not on PyPI: .ci/setup.d/10-interfaces.sh builds it where it is missing
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None

_LEVEL = {"ok": Level.OK, "warn": Level.WARN, "error": Level.ERROR, "unknown": Level.WARN}


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

    def __post_init__(self) -> None:
        if not self.period > 0:
            raise ValueError(f"period must be > 0 s, got {self.period}")
        if self.confirm < 1:
            raise ValueError(f"confirm must be >= 1, got {self.confirm}")
        camera_topics(self.cameras)  # raises naming a bad or repeated name


@dataclass
class _Camera:
    """What the monitor holds about one camera."""

    inputs: CameraInputs
    calibrated: Pose | None = None
    calibration_source: str = "none"
    reference: DriftReport | None = None
    referenced: bool = False  # the first check after this calibration has been made
    last: DriftReport | None = None
    shown: str = "unknown"  # the level published (after confirmation)
    streak: list[str] = field(default_factory=list)  # levels of the latest checks
    checks: int = 0
    recalibrating: bool = False


class CalibrationMonitorNode(Node):
    def __init__(self) -> None:
        super().__init__("calibration_monitor")
        self.opts = declare_and_read(self, MonitorParams())
        self.engine = declare_and_read(self, CalibrationParams(), prefix="engine.")
        self.drift = declare_and_read(self, DriftParams(), prefix="drift.")
        from semcal_ros.engine.drift import check_params
        from semcal_ros.engine.problem import mapping_for

        user = LabelMapping.from_yaml(self.opts.label_mapping) if self.opts.label_mapping \
            else None
        self.mapping = mapping_for(check_params(self.engine, self.drift), user)
        self._lock = threading.Lock()
        self._map: HeldMap | None = None
        self._map_refusal = ""
        self._tf_static: dict[str, TransformStamped] = {}
        self.cameras = {t.name: _Camera(CameraInputs(t, self.get_logger().error,
                                                     self.resolve_topic_name))
                        for t in camera_topics(self.opts.cameras)}
        if self.opts.map_file:
            from semcal_ros.io.ply import read_ply

            self._map = HeldMap.from_cloud(read_ply(self.opts.map_file).finite(), self.mapping,
                                           self.opts.map_frame, self.opts.map_file)
            self.get_logger().info(f"map from {self.opts.map_file}: {self._map.points} points")
        if self.opts.calibration_file:
            self._load_calibration_files()

        inputs = MutuallyExclusiveCallbackGroup()
        checks = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, "map", self._on_map, qos.latched(),
                                 callback_group=inputs)
        for cam in self.cameras.values():
            cam.inputs.subscribe(self, inputs)
        self.create_subscription(TransformStamped, "calibration/transform", self._on_transform,
                                 qos.latched(), callback_group=inputs)
        if TFMessage is not None:
            self.create_subscription(TFMessage, "/tf_static", self._on_tf_static,
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
    def _load_calibration_files(self) -> None:
        from semcal_ros.io.files import read_pose

        for name, cam in self.cameras.items():
            path = self.opts.calibration_file.replace("{name}", name or "camera")
            try:
                self._set_calibration(cam, read_pose(path), f"file {path}")
            except (ValueError, OSError) as exc:
                self.get_logger().error(f"ignoring calibration_file for "
                                        f"{cam.inputs.topics.label}: {exc}")

    def _on_map(self, msg: PointCloud2) -> None:
        try:
            cloud = conv.pointcloud2_to_cloud(msg, require_label=True).finite()
            held = HeldMap.from_cloud(cloud, self.mapping, msg.header.frame_id
                                      or self.opts.map_frame, "topic")
        except ValueError as exc:
            if str(exc) != self._map_refusal:
                self.get_logger().error(f"ignoring map: {exc}; keeping the map held")
            self._map_refusal = str(exc)
            return
        with self._lock:
            self._map, self._map_refusal = held, ""
            for cam in self.cameras.values():  # a new map: new references
                cam.reference, cam.referenced = None, False
        self.get_logger().info(f"map received: {held.points} points")

    def _camera_of(self, frame_id: str, unframed: bool = True) -> _Camera | None:
        for cam in self.cameras.values():
            if cam.inputs.answers_to(frame_id):
                return cam
        if unframed and len(self.cameras) == 1 and "" in self.cameras:
            cam = self.cameras[""]
            # the single camera before its CameraInfo came: the calibrator's usual frame
            snap = cam.inputs.snapshot()
            if not snap.frame_id:
                return cam
        return None

    def _on_transform(self, msg: TransformStamped) -> None:
        self._take_transform(msg, "calibration/transform")

    def _on_tf_static(self, msg: Any) -> None:
        # kept: /tf_static is latched and comes once, maybe before a camera's CameraInfo says
        # which frame is its own
        with self._lock:
            self._tf_static = {tf.child_frame_id: tf for tf in msg.transforms
                               if tf.header.frame_id == self._map_frame_locked()}
        self._match_tf_static()

    def _match_tf_static(self) -> None:
        with self._lock:
            pending = list(self._tf_static.values())
        for tf in pending:
            self._take_transform(tf, "/tf_static", quiet=True)

    def _map_frame(self) -> str:
        with self._lock:
            return self._map_frame_locked()

    def _map_frame_locked(self) -> str:
        return self._map.frame if self._map is not None else self.opts.map_frame

    def _take_transform(self, msg: TransformStamped, source: str, quiet: bool = False) -> None:
        cam = self._camera_of(msg.child_frame_id, unframed=not quiet)
        if cam is None:
            if not quiet:
                self.get_logger().warning(f"ignoring {source}: no monitored camera has frame "
                                          f"'{msg.child_frame_id}'")
            return
        if msg.header.frame_id and msg.header.frame_id != self._map_frame():
            self.get_logger().error(f"ignoring {source} for '{msg.child_frame_id}': it is in "
                                    f"'{msg.header.frame_id}', the map in '{self._map_frame()}'")
            return
        tr, rot = msg.transform.translation, msg.transform.rotation
        q = np.array([rot.x, rot.y, rot.z, rot.w])
        if not (np.all(np.isfinite([tr.x, tr.y, tr.z])) and np.all(np.isfinite(q))
                and abs(np.linalg.norm(q) - 1.0) < 1e-3):
            self.get_logger().error(f"ignoring {source} for '{msg.child_frame_id}': not a "
                                    "finite pose with a unit quaternion")
            return
        pose = conv.pose_from_transform(msg)
        self._set_calibration(cam, pose, source)

    def _set_calibration(self, cam: _Camera, pose: Pose, source: str) -> None:
        with self._lock:
            same = cam.calibrated is not None and \
                np.allclose(cam.calibrated.vector(), pose.vector(), atol=1e-9)
            if same:
                return
            cam.calibrated, cam.calibration_source = pose, source
            cam.reference, cam.referenced, cam.streak, cam.recalibrating = None, False, [], False
        self.get_logger().info(f"calibration of {cam.inputs.topics.label} from {source}")

    # --- the checks ---------------------------------------------------------------------------
    def check_all(self) -> None:
        self._match_tf_static()
        for cam in self.cameras.values():
            try:
                self.check(cam)
            except Exception as exc:  # a check must never take the node down
                self.get_logger().error(f"check of {cam.inputs.topics.label} failed: {exc}")

    def check(self, cam: _Camera) -> DriftReport:
        snap = cam.inputs.snapshot()
        with self._lock:
            held, pose, reference = self._map, cam.calibrated, cam.reference
        report: DriftReport
        if held is None:
            report = _unknown(pose, "no map yet")
        elif pose is None:
            report = _unknown(pose, "no calibration yet (/tf_static, calibration/transform or "
                                    "calibration_file)")
        elif snap.camera is None:
            report = _unknown(pose, "no CameraInfo yet")
        else:
            checker = DriftChecker(EMPTY_CLOUD, snap.camera, pose, self.engine, self.drift,
                                   prepared=held.prepared)
            report = checker.check(snap.labels, reference=reference)
            if report.judged and not cam.referenced:
                with self._lock:
                    cam.referenced = True
                    if report.level == "ok":
                        cam.reference = report
                        report = DriftReport(
                            "ok", "reference check: later checks count drift from here",
                            pose, report.estimated, 0.0, 0.0, (0.0, 0.0, 0.0),
                            report.loss_calibrated, report.loss_best, report.coverage,
                            report.evaluations, report.seconds)
        self._publish(cam, report, snap.labels_frame or snap.frame_id)
        return report

    def _publish(self, cam: _Camera, report: DriftReport, frame_id: str) -> None:
        with self._lock:
            cam.checks += 1
            cam.last = report
            cam.streak = (cam.streak + [report.level])[-self.opts.confirm:]
            confirmed = len(cam.streak) == self.opts.confirm and len(set(cam.streak)) == 1
            if confirmed or report.level in ("ok", "unknown"):
                cam.shown = report.level
            shown = cam.shown
        msg = CalibrationDrift(camera_frame_id=frame_id or cam.inputs.name,
                               level=int(_LEVEL[shown]) if shown != "unknown" else 1)
        msg.header = conv.make_header(self._map_frame())
        pending = report.level != shown
        msg.message = (f"{'cannot judge: ' if not report.judged else ''}{report.message}"
                       + (f" (confirming {len(cam.streak)}/{self.opts.confirm})"
                          if pending and report.judged else ""))
        msg.drift_translation_m = float(report.drift_translation_m)
        msg.drift_rotation_deg = float(report.drift_rotation_deg)
        msg.drift_xyz_m.x, msg.drift_xyz_m.y, msg.drift_xyz_m.z = report.drift_xyz_m
        msg.loss_calibrated = float(report.loss_calibrated)
        msg.loss_best = float(report.loss_best)
        if report.calibrated is not None:
            msg.calibrated_pose = conv.pose_to_msg(report.calibrated)
        if report.estimated is not None:
            msg.estimated_pose = conv.pose_to_msg(report.estimated)
        msg.seconds = float(report.seconds)
        self.drift_pubs[cam.inputs.name].publish(msg)
        if shown in ("warn", "error") and not pending:
            self.get_logger().warning(f"{cam.inputs.topics.label}: {shown.upper()}: "
                                      f"{report.message}")
        if shown == "error" and self.client is not None and not cam.recalibrating:
            self._recalibrate(cam, report, frame_id)

    def _recalibrate(self, cam: _Camera, report: DriftReport, frame_id: str) -> None:
        from semcal_ros.ros.client import make_goal

        if not self.client.server_is_ready():
            self.get_logger().error(f"auto_recalibrate: action '{self.opts.calibrate_action}' "
                                    "is not available")
            return
        cam.recalibrating = True
        start = report.estimated or report.calibrated
        goal = make_goal(start, self._map_frame(), cam.inputs.name or frame_id)
        self.client.send_goal_async(goal)
        self.get_logger().warning(f"auto_recalibrate: goal sent for {cam.inputs.topics.label} "
                                  "(the calibrator publishes the new transform)")

    # --- diagnostics --------------------------------------------------------------------------
    def _camera_report(self, cam: _Camera) -> Report:
        with self._lock:
            last, shown = cam.last, cam.shown
            values: dict[str, Any] = {"calibration_source": cam.calibration_source,
                                      "checks": cam.checks,
                                      "reference": "yes" if cam.reference else "no"}
        values.update(cam.inputs.values())
        refusals = cam.inputs.refusals()
        if last is None:
            return Level.WARN, "no check yet", values
        values.update({"drift_cm": round(last.drift_translation_m * 100, 2),
                       "drift_deg": round(last.drift_rotation_deg, 4),
                       "drift_xyz_cm": "/".join(f"{v * 100:.1f}" for v in last.drift_xyz_m),
                       "loss_calibrated": last.loss_calibrated, "loss_best": last.loss_best,
                       "check_seconds": round(last.seconds, 3), "last_level": last.level})
        if refusals:
            return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in refusals.items()), values
        if shown == "unknown":
            return Level.WARN, f"cannot judge: {last.message}", values
        return _LEVEL[shown], f"{shown.upper()}: {last.message}" if shown != "ok" else \
            last.message, values

    def _camera_reports(self) -> dict[str, Report]:
        return {name: self._camera_report(cam) for name, cam in self.cameras.items()}

    def _report(self) -> Report:
        with self._lock:
            held = self._map
        values: dict[str, Any] = {"map_points": held.points if held is not None else 0,
                                  "period": self.opts.period}
        if self._map_refusal:
            values["input_error.map"] = self._map_refusal
        if "" in self.cameras:
            level, message, cam_values = self._camera_report(self.cameras[""])
            return level, message, {**values, **cam_values}
        parts = self._camera_reports()
        worst = max((p[0] for p in parts.values()), default=Level.OK)
        flagged = [n for n, p in parts.items() if p[0] == worst and worst != Level.OK]
        return worst, (f"{len(parts)} cameras" + (f"; {', '.join(flagged)}: "
                                                  f"{worst.name}" if flagged else ": OK")), values


def _unknown(pose: Pose | None, message: str) -> DriftReport:
    return DriftReport("unknown", message, pose)


def main(args: list[str] | None = None) -> int:
    return run_node(CalibrationMonitorNode, threads=3, args=args)


if __name__ == "__main__":
    sys.exit(main())
