"""``calibrator``: the Calibrate action server, for one camera or several on one map.

Holds the latest labelled map (``map``, transient local, or ``map_file``), prepared once per map
and shared by every camera and goal (:mod:`semcal_ros.ros.held_map`). Per camera it holds the
newest label image, CameraInfo and camera image (:mod:`semcal_ros.ros.camera_inputs`): with the
``cameras`` parameter empty, one unnamed camera on ``camera/labels``, ``camera/camera_info`` and
``camera/image_raw``; with ``cameras: [north, south]``, ``north/labels`` ... ``south/image_raw``.
All topic names are relative, so remap them or push the node into a namespace.

A goal names its camera by ``camera_frame_id`` (the frame id of its CameraInfo / label image, or
its name; empty with a single camera). Goals run one after another on one long-lived engine
thread (:mod:`semcal_ros.ros.engine_job`): a goal for another camera waits in the queue (its
feedback says "queued"); a second goal for a camera already running or queued is accepted and
aborted at once with the reason (the action protocol's rejection carries none). A goal that
cannot run is aborted with a message naming every problem (:mod:`semcal_ros.engine.validation`, shared
with ``semcal calibrate``), and a degenerate best pose is never published. Input messages that
cannot be used are refused with the reason logged and in the diagnostics, and what the node held
is kept.

The result goes to the caller (with the quality report: verdict, agreement, coverage, per-axis
uncertainty), to ``calibration/transform`` (TransformStamped, transient local), to ``/tf_static``
(one TFMessage holding the transforms of every camera calibrated so far, as tf2's static
broadcaster does) and, as a picture of the map rendered at the result over the camera image with
the verdict drawn on it, to ``calibration/overlay``. /diagnostics carries the node's status and,
with named cameras, one status per camera (``calibrator/<name>``): its inputs, its goal and the
verdict of its last result (WARN inconclusive, ERROR failed).
"""

from __future__ import annotations

import copy
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped, Vector3
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2

from semcal_interfaces.action import Calibrate
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import LabelMapping, colorize
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine import validation
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.calibrate_goal import Inputs, Request, goal_request, input_problems
from semcal_ros.ros.camera_inputs import CameraInputs, camera_topics
from semcal_ros.ros.diagnostics import Diagnostics, Level, Report
from semcal_ros.ros.engine_job import EngineJob, GoalRunner, GoalState, JobCancelled
from semcal_ros.ros.held_map import EMPTY_CLOUD, HeldMap
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import run_node

try:  # not on PyPI: .ci/setup.d/10-interfaces.sh builds it where it is missing
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None

#: Executor threads besides one per camera (a goal waiting for the engine holds one thread).
BASE_THREADS = 4


@dataclass
class CalibratorNodeParams:
    """The node's own parameters; the engine's are :class:`CalibrationParams` (``engine.*``)."""

    map_file: str = ""  # labelled PLY loaded at start (a map from elsewhere); the topic still wins
    map_frame: str = "map"  # frame of map_file and of map messages without a frame id
    label_mapping: str = ""  # YAML of the label alignment (empty: the built-in default)
    cameras: tuple[str, ...] = ()  # camera names (topics <name>/labels ...); empty: camera/...
    seed: int = 0  # of the verification starts when the goal gives none (negative: random)
    feedback_period: float = 0.5  # s between feedback messages while a goal runs
    diagnostics_period: float = 1.0  # s between /diagnostics messages (0: off)
    publish_tf_static: bool = True  # also publish the result on /tf_static
    overlay_file: str = ""  # also write the overlay picture here (PNG) after each success
    image_transport: str = "raw"  # camera image: raw, or compressed (<image_raw>/compressed)
    labels_transport: str = "raw"  # label image: raw, or compressed (PNG only; JPEG refused)

    def __post_init__(self) -> None:
        if not 0 < self.feedback_period <= 1.0:
            raise ValueError("feedback_period must be in (0, 1] s (feedback at least once a "
                             f"second), got {self.feedback_period}")
        camera_topics(self.cameras)  # raises naming a bad or repeated name


@dataclass
class _Outcome:
    """What the engine thread hands back for one goal."""

    result: Any  # semcal_ros.engine.results.CalibrationResult
    overlay: np.ndarray | None = None  # RGB, rendered for a result worth publishing
    overlay_error: str = ""


@dataclass
class _LastResult:
    message: str
    quality: Any = None  # QualityReport of the last success


class CalibratorNode(Node):
    def __init__(self) -> None:
        super().__init__("calibrator")
        self.opts = declare_and_read(self, CalibratorNodeParams())
        self.defaults = declare_and_read(self, CalibrationParams(), prefix="engine.")
        validation.check(validation.output_problems(self.opts.overlay_file,
                                                    "parameter 'overlay_file':"))
        from semcal_ros.engine.problem import mapping_for

        self.mapping = LabelMapping.from_yaml(self.opts.label_mapping) \
            if self.opts.label_mapping else LabelMapping()
        # the alignment every goal's Problem uses (goals cannot change labels.merge), so the
        # map is prepared with it once
        self.map_mapping = mapping_for(self.defaults, self.mapping)
        self._lock = threading.Lock()
        self._map: HeldMap | None = None
        self._map_refusal = ""
        self.cameras = {t.name: CameraInputs(t, self.get_logger().error, self.resolve_topic_name,
                                             self.opts.image_transport, self.opts.labels_transport,
                                             self.get_logger().warning)
                        for t in camera_topics(self.opts.cameras)}
        self._last: dict[str, _LastResult] = {}
        self._tf: dict[str, TransformStamped] = {}  # child frame -> its latest transform
        self.last_result = ""
        if self.opts.map_file:
            self._load_map_file(self.opts.map_file)

        inputs = MutuallyExclusiveCallbackGroup()
        timers = MutuallyExclusiveCallbackGroup()
        overrides = qos.overridable()
        self.create_subscription(PointCloud2, "map", self._on_map, qos.latched(),
                                 callback_group=inputs, qos_overriding_options=overrides)
        for camera in self.cameras.values():
            camera.subscribe(self, inputs, overrides)
        self.result_pub = self.create_publisher(
            TransformStamped, "calibration/transform", qos.latched(),
            qos_overriding_options=overrides)
        self.overlay_pub = self.create_publisher(Image, "calibration/overlay", qos.latched(),
                                                 qos_overriding_options=overrides)
        self.tf_pub = None
        if self.opts.publish_tf_static:
            if TFMessage is None:
                self.get_logger().warning(
                    "tf2_msgs is not installed: the result is published on "
                    "calibration/transform only (not on /tf_static)")
            else:
                self.tf_pub = self.create_publisher(TFMessage, "/tf_static", qos.latched())
        self.action = ActionServer(
            self, Calibrate, "calibrate", execute_callback=self._execute,
            goal_callback=lambda _: GoalResponse.ACCEPT,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.goals = GoalRunner(self, self.opts.feedback_period, self._feedback, timers,
                                worker_name="calibrate")
        self.diagnostics = Diagnostics(
            self, self._report, self.opts.diagnostics_period, callback_group=timers,
            parts=self._camera_reports if self._named else None)
        labels = ", ".join(f"'{self.resolve_topic_name(c.topics.labels)}'"
                           for c in self.cameras.values())
        self.get_logger().info(
            f"ready: action '{self.resolve_topic_name('calibrate')}', map on "
            f"'{self.resolve_topic_name('map')}', labels on {labels}")

    @property
    def _named(self) -> bool:
        return "" not in self.cameras

    # --- the map ----------------------------------------------------------------------------
    def _load_map_file(self, path: str) -> None:
        from semcal_ros.io.ply import read_ply

        held = HeldMap.from_cloud(read_ply(path).finite(), self.map_mapping,
                                  self.opts.map_frame, path)
        with self._lock:
            self._map = held
        self.get_logger().info(f"map from {path}: {held.points} points (prepared in "
                               f"{held.seconds:.1f} s)")

    def _usable_map(self, msg: PointCloud2) -> LabelledCloud:
        """The map's finite points; ValueError (the held map is kept) when none is left."""
        raw = conv.pointcloud2_to_cloud(msg, require_label=True)
        cloud = raw.finite()
        if len(cloud) == 0:
            what = "is empty" if len(raw) == 0 else \
                f"has no finite point ({len(raw)} points, all NaN or infinite)"
            raise ValueError(f"the map message {what}; keeping the map held ({self._held()})")
        if len(cloud) < len(raw):
            self.get_logger().warning(f"map: {len(raw) - len(cloud)} of {len(raw)} points are "
                                      f"NaN or infinite and were dropped")
        return cloud

    def _held(self) -> str:
        with self._lock:
            return f"{self._map.points} points" if self._map is not None else "none"

    def _on_map(self, msg: PointCloud2) -> None:
        try:
            cloud = self._usable_map(msg)
            frame = msg.header.frame_id or self.opts.map_frame
            held = HeldMap.from_cloud(cloud, self.map_mapping, frame, "topic")
        except ValueError as exc:
            text = str(exc)
            if "keeping the map held" not in text:
                text = f"{text}; keeping the map held ({self._held()})"
            if text != self._map_refusal:
                self.get_logger().error(f"ignoring map: {text}")
            self._map_refusal = text
            return
        del cloud  # only the prepared map stays
        with self._lock:
            first = self._map is None or self._map.source != "topic"
            self._map, self._map_refusal = held, ""
        if first:
            self.get_logger().info(f"map received: {held.points} points in '{held.frame}' "
                                   f"(prepared in {held.seconds:.1f} s)")

    def inputs(self, camera: CameraInputs) -> Inputs:
        snap = camera.snapshot()
        with self._lock:
            held = self._map
        return Inputs(held, held.frame if held is not None else self.opts.map_frame,
                      snap.labels, snap.labels_frame, snap.camera,
                      self.resolve_topic_name("map"),
                      self.resolve_topic_name(camera.topics.labels),
                      self.resolve_topic_name(camera.topics.camera_info))

    # --- the action ------------------------------------------------------------------------
    def _camera_for(self, camera_frame_id: str) -> tuple[CameraInputs | None, str]:
        """The camera a goal means, and the frame id to check its inputs against; or None and
        the reason."""
        if len(self.cameras) == 1 and not self._named:
            return self.cameras[""], camera_frame_id  # the inputs' check names a wrong frame
        served = ", ".join(f"'{c.name}'" + (f" ({c.snapshot().frame_id})"
                                            if c.snapshot().frame_id else "")
                           for c in self.cameras.values())
        if not camera_frame_id:
            if len(self.cameras) == 1:
                return next(iter(self.cameras.values())), ""
            return None, (f"camera_frame_id is empty but this calibrator serves cameras "
                          f"{served}: name one")
        if camera_frame_id in self.cameras:
            return self.cameras[camera_frame_id], ""  # by name: any frame id of that camera
        for camera in self.cameras.values():
            if camera.answers_to(camera_frame_id):
                return camera, camera_frame_id
        return None, f"unknown camera '{camera_frame_id}': this calibrator serves {served}"

    def _execute(self, handle: Any) -> Calibrate.Result:
        """Validate, queue the goal on the engine thread, and answer it as soon as it is done
        or cancelled (see :mod:`semcal_ros.ros.engine_job`)."""
        goal_id = bytes(handle.goal_id.uuid).hex()[:8]
        camera, frame = self._camera_for(handle.request.camera_frame_id)
        if camera is None:
            return self._finish(handle, "abort", f"invalid goal: {frame}")
        state = self.goals.claim(camera.name, goal_id, handle)
        if isinstance(state, str):
            return self._finish(handle, "abort", state)
        job = None
        try:
            inputs = self.inputs(camera)
            goal = handle.request
            if frame != goal.camera_frame_id:
                goal = copy.copy(goal)
                goal.camera_frame_id = frame
            try:
                request = goal_request(goal, inputs, self.defaults, self.opts.seed)
            except ValueError as exc:
                return self._finish(handle, "abort", f"invalid goal: {exc}")
            ahead = sum(1 for k, s in self.goals.states().items()
                        if k != camera.name and s.submitted)
            self.get_logger().info(
                f"goal {goal_id}: calibrating '{request.camera_frame}' against a map of "
                f"{inputs.map.points} points from {np.round(request.initial.translation, 3)}"
                + (f" (queued behind {ahead} goal{'s' * (ahead > 1)})" if ahead else ""))
            job = EngineJob(lambda j: self._calibrate(j, state, inputs, request, camera),
                            stop_also=lambda: not self.context.ok(),
                            log_error=self.get_logger().error)
            outcome = self.goals.run(state, job)
            if outcome == "cancelled":
                return self._cancelled(handle, job, state)
            if outcome == "shutdown":
                return self._finish(handle, "abort", "the calibrator is shutting down")
            return self._answer(handle, job, camera, request)
        finally:
            self.goals.release(state, job)

    def _calibrate(self, job: EngineJob, state: GoalState, inputs: Inputs, request: Request,
                   camera: CameraInputs) -> _Outcome:
        """(engine thread) The engine's procedure on the shared prepared map, then the
        overlay."""
        from semcal_ros.engine.search import solve
        from semcal_ros.engine.problem import Problem

        t0 = time.perf_counter()
        problem = Problem(EMPTY_CLOUD, inputs.labels, inputs.camera, request.initial.translation,
                          request.params, self.mapping, prepared=inputs.map.prepared)
        result = solve(problem, request.initial, request.seed,
                       lambda p: self.goals.progress(state, p), job.should_stop)
        result.seconds = time.perf_counter() - t0
        out = _Outcome(result)
        if not validation.result_problems(float(result.loss), request.params):
            try:  # here, not in an executor thread: the engine's thread does the heavy work
                out.overlay = self._overlay(problem, result, inputs.labels, camera)
            except Exception as exc:  # noqa: BLE001 - a by-product; the result stands
                out.overlay_error = f"{type(exc).__name__}: {exc}"
        return out

    def _overlay(self, problem: Any, result: Any, labels: np.ndarray, camera: CameraInputs
                 ) -> np.ndarray:
        """The map rendered at the result over the camera's newest image (the label colours
        without one), exactly as the engine renders it, with the verdict drawn on it."""
        from semcal_ros.engine.overlay import annotate_quality, blend_labels

        model = problem.camera
        rgb = camera.snapshot().rgb
        if rgb is None or rgb.shape[:2] != (model.height, model.width):
            rgb = colorize(labels)  # no matching camera image: draw over the labels
        picture = blend_labels(rgb, problem.render(result.pose))
        return annotate_quality(picture, result.quality) if result.quality is not None \
            else picture

    def _answer(self, handle: Any, job: EngineJob, camera: CameraInputs, request: Request
                ) -> Calibrate.Result:
        if job.error is not None:
            from semcal_ros.engine.search import Cancelled

            exc = job.error
            if isinstance(exc, (Cancelled, JobCancelled)):
                if handle.is_cancel_requested:
                    return self._cancelled(handle, job, None)
                return self._finish(handle, "abort", "the calibrator is shutting down")
            if isinstance(exc, ValueError):
                text = str(exc)
                if not text.startswith("calibration failed"):  # the engine may say it already
                    text = f"calibration failed: {text}"
                return self._finish(handle, "abort", text, seconds=job.seconds(),
                                    camera=camera.name)
            return self._finish(handle, "abort", f"internal error: {type(exc).__name__}: {exc}",
                                seconds=job.seconds(), camera=camera.name)
        out: _Outcome = job.result
        result = out.result
        degenerate = validation.result_problems(float(result.loss), request.params)
        if degenerate:
            return self._finish(handle, "abort", f"calibration failed: {'; '.join(degenerate)}",
                                evaluations=int(result.evaluations),
                                seconds=float(result.seconds), camera=camera.name)
        transform = conv.transform_from_pose(result.pose, request.map_frame,
                                             request.camera_frame,
                                             self.get_clock().now().to_msg())
        self._publish_result(transform, out, camera)
        rpy = result.pose.body_rpy_deg()
        q = result.quality
        message = (f"calibrated '{request.camera_frame}': t = "
                   f"[{', '.join(f'{v:.3f}' for v in result.pose.translation)}] m, rpy = "
                   f"[{', '.join(f'{v:.2f}' for v in rpy)}] deg, loss {result.loss:.5f}, "
                   f"{result.accepted}/{len(result.runs)} runs agree within "
                   f"{result.spread_translation_m * 100:.1f} cm / "
                   f"{result.spread_rotation_deg:.3f} deg, {result.seconds:.1f} s"
                   + (f", verdict {q.verdict}" if q is not None else ""))
        if q is not None:
            self.get_logger().info(f"quality of '{request.camera_frame}': {q.summary()}")
        return self._finish(handle, "succeed", message, transform=transform,
                            loss=float(result.loss),
                            spread_translation_m=float(result.spread_translation_m),
                            spread_rotation_deg=float(result.spread_rotation_deg),
                            evaluations=int(result.evaluations), seconds=float(result.seconds),
                            camera=camera.name, quality=q, **_quality_fields(q))

    def _cancelled(self, handle: Any, job: EngineJob, state: GoalState | None
                   ) -> Calibrate.Result:
        evaluations = state.evaluations if state is not None else 0
        seconds = job.seconds()
        return self._finish(handle, "canceled", f"cancelled after {seconds:.1f} s "
                            f"({evaluations} evaluations reported)", evaluations=evaluations,
                            seconds=seconds)

    def _finish(self, handle: Any, outcome: str, message: str, camera: str | None = None,
                quality: Any = None, **fields: Any) -> Calibrate.Result:
        result = Calibrate.Result(success=outcome == "succeed", message=message, **fields)
        try:
            getattr(handle, outcome)()
        except Exception:  # noqa: BLE001 - the action server goes away with the node
            if self.context.ok():
                raise
            return result
        if camera is not None or len(self.cameras) == 1:
            key = camera if camera is not None else next(iter(self.cameras))
            previous = self._last.get(key)
            # a failure keeps the verdict of the transform that stays published
            kept = quality if outcome == "succeed" else (previous.quality if previous else None)
            self._last[key] = _LastResult(message, kept)
        self.last_result = message
        past = {"succeed": "succeeded", "abort": "aborted", "canceled": "cancelled"}[outcome]
        # rclpy binds a severity to each logging call site: one site per severity, never shared
        if outcome == "succeed":
            self.get_logger().info(f"goal {past}: {message}")
        else:
            self.get_logger().warning(f"goal {past}: {message}")
        return result

    def close(self) -> None:
        self.goals.close()

    def _publish_result(self, transform: TransformStamped, out: _Outcome,
                        camera: CameraInputs) -> None:
        self.result_pub.publish(transform)
        if self.tf_pub is not None:
            with self._lock:
                self._tf[transform.child_frame_id] = transform
                every = list(self._tf.values())
            self.tf_pub.publish(TFMessage(transforms=every))
        if out.overlay is None:
            self.get_logger().error(f"overlay failed: {out.overlay_error}")
            return
        self.overlay_pub.publish(conv.numpy_to_image(
            np.ascontiguousarray(out.overlay, np.uint8), "rgb8",
            conv.make_header(transform.child_frame_id, transform.header.stamp)))
        if self.opts.overlay_file:
            from semcal_ros.io.files import write_rgb_image

            try:
                write_rgb_image(self.opts.overlay_file, out.overlay)
                self.get_logger().info(f"overlay written to {self.opts.overlay_file}")
            except OSError as exc:
                self.get_logger().error(f"overlay not written: {exc}")

    def _feedback(self, state: GoalState) -> Calibrate.Feedback:
        feedback = Calibrate.Feedback(stage=state.stage, evaluations=state.evaluations,
                                      best_loss=float(state.best_loss),
                                      elapsed_seconds=time.monotonic() - state.accepted)
        if state.best_pose is not None:
            feedback.best_pose = conv.pose_to_msg(state.best_pose)
        return feedback

    # --- diagnostics -----------------------------------------------------------------------
    def _state(self, name: str) -> str:
        s = self.goals.state(name)
        if s is None:
            return "idle"
        if s.stage == "queued":
            return f"queued {s.goal_id}"
        return f"running {s.goal_id} ({s.stage}, {s.evaluations} evaluations)"

    def _map_values(self) -> dict[str, Any]:
        with self._lock:
            held = self._map
        values: dict[str, Any] = {
            "map_points": held.points if held is not None else 0,
            "map_points_prepared": len(held.prepared.xyz) if held is not None else 0,
            "map_frame": held.frame if held is not None else self.opts.map_frame,
            "map_source": held.source if held is not None else "none",
        }
        if self._map_refusal:
            values["input_error.map"] = self._map_refusal
        return values

    def _camera_report(self, camera: CameraInputs, missing: list[str]) -> Report:
        """Level, message and values of one camera (or of the node with its single camera)."""
        values = camera.values()
        last = self._last.get(camera.name)
        values["state"] = self._state(camera.name)
        values["last_result"] = last.message if last else "none"
        values.update(_quality_values(last.quality if last else None))
        refusals = camera.refusals()
        if refusals:
            return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in refusals.items()), values
        if missing:
            return Level.WARN, "; ".join(missing), values
        running = values["state"] != "idle"
        q = last.quality if last else None
        if q is not None and q.verdict != "good" and not running:
            level = Level.ERROR if q.verdict == "failed" else Level.WARN
            return level, f"last calibration {q.verdict}: {q.reason}", values
        return Level.OK, "calibrating" if running else "ready", values

    def _report(self) -> Report:
        """The node's status; with the single unnamed camera it is that camera's too."""
        values = self._map_values()
        values["last_rejection"] = self.goals.last_rejection or "none"
        map_error = values.get("input_error.map")
        if not self._named:
            camera = self.cameras[""]
            missing = input_problems("", self.inputs(camera))
            level, message, cam_values = self._camera_report(camera, missing)
            values = {**values, **cam_values}
            if map_error:
                errors = {"map": map_error, **camera.refusals()}
                return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in errors.items()), values
            return level, message, values
        states = {name: self._state(name) for name in self.cameras}
        busy = {n: s for n, s in states.items() if s != "idle"}
        values["state"] = "; ".join(f"{n}: {s}" for n, s in busy.items()) or "idle"
        values["cameras"] = ", ".join(self.cameras)
        values["last_result"] = self.last_result or "none"
        if map_error:
            return Level.ERROR, f"map: {map_error}", values
        if values["map_source"] == "none":
            return Level.WARN, f"no map received yet (topic '{self.resolve_topic_name('map')}')", \
                values
        return Level.OK, "calibrating" if busy else "ready", values

    def _camera_reports(self) -> dict[str, Report]:
        return {name: self._camera_report(camera, camera.problems())
                for name, camera in self.cameras.items()}


def _quality_fields(q: Any) -> dict[str, Any]:
    """The Calibrate result's quality fields from a QualityReport (none: left empty)."""
    if q is None:
        return {}
    return {"verdict": q.verdict, "verdict_reason": q.reason, "agreement": float(q.agreement),
            "agreement_classes": list(q.agreement_per_class),
            "agreement_per_class": [float(v) for v in q.agreement_per_class.values()],
            "coverage": float(q.coverage),
            "uncertainty_translation_m": Vector3(
                **dict(zip("xyz", map(float, q.uncertainty_translation_m)))),
            "uncertainty_rpy_deg": Vector3(**dict(zip("xyz", map(float, q.uncertainty_rpy_deg))))}


def _quality_values(q: Any) -> dict[str, Any]:
    """The verdict and its figures as /diagnostics key/values."""
    if q is None:
        return {"verdict": "none"}
    ut, ur = q.uncertainty_translation_m, q.uncertainty_rpy_deg
    return {"verdict": q.verdict, "verdict_reason": q.reason,
            "agreement": round(float(q.agreement), 4), "coverage": round(float(q.coverage), 4),
            "uncertainty_cm": "/".join(f"{v * 100:.1f}" for v in ut),
            "uncertainty_deg": "/".join(f"{v:.3f}" for v in ur)}


def main(args: list[str] | None = None) -> int:
    return run_node(CalibratorNode, threads=lambda node: BASE_THREADS + len(node.cameras),
                    args=args)


if __name__ == "__main__":
    sys.exit(main())
