"""``calibrator``: the Calibrate action server.

Holds the latest labelled map (``map``, transient local), label image (``camera/labels``, mono8
trainIds), CameraInfo (``camera/camera_info``) and camera image (``camera/image_raw``, for the
overlay); all topic names are relative, so remap them (``-r map:=/other/map``) or push the node
into a namespace. A goal runs :func:`semcal_ros.optimize.calibrate` in a thread of its own, while
the executor (MultiThreadedExecutor, reentrant action group) keeps serving feedback (a timer, at
least once a second), cancel requests and new messages; a cancel is answered at once and the engine
stops at its next check. One goal at a time: a goal that arrives while another runs is accepted
and aborted at once with the reason (the action protocol's rejection carries none). A goal that
cannot run is aborted with a message naming every problem (:mod:`semcal_ros.validation`, shared
with ``semcal calibrate``), and a degenerate best pose is never published. Input messages that
cannot be used (an empty or all-NaN map, a CameraInfo with NaN intrinsics ...) are refused with
the reason logged and in the diagnostics, and what the node held is kept. The result goes to the caller, to
``calibration/transform`` (TransformStamped, transient local), to ``/tf_static`` (tf2_msgs
TFMessage) and, as a picture of the map rendered at the result over the camera image, to
``calibration/overlay``.
"""

from __future__ import annotations

import math
import sys
import queue
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from semcal_interfaces.action import Calibrate
from semcal_ros.cloud import LabelledCloud
from semcal_ros.labels import LabelMapping, colorize
from semcal_ros.params import CalibrationParams
from semcal_ros.pose import Pose
from semcal_ros import validation
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.calibrate_goal import Inputs, Request, goal_request, input_problems
from semcal_ros.ros.diagnostics import Diagnostics, Level
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import release_free_memory, run_node

try:  # not on PyPI: .ci/setup.d/10-interfaces.sh builds it where it is missing
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None


@dataclass
class CalibratorNodeParams:
    """The node's own parameters; the engine's are :class:`CalibrationParams` (``engine.*``)."""

    map_file: str = ""  # labelled PLY loaded at start (a map from elsewhere); the topic still wins
    map_frame: str = "map"  # frame of map_file and of map messages without a frame id
    label_mapping: str = ""  # YAML of the label alignment (empty: the built-in default)
    seed: int = 0  # of the verification starts when the goal gives none (negative: random)
    feedback_period: float = 0.5  # s between feedback messages while a goal runs
    diagnostics_period: float = 1.0  # s between /diagnostics messages (0: off)
    publish_tf_static: bool = True  # also publish the result on /tf_static
    overlay_file: str = ""  # also write the overlay picture here (PNG) after each success

    def __post_init__(self) -> None:
        if not 0 < self.feedback_period <= 1.0:
            raise ValueError("feedback_period must be in (0, 1] s (feedback at least once a "
                             f"second), got {self.feedback_period}")


@dataclass
class _Run:
    """The goal being worked on."""

    goal_id: str
    started: float
    stage: str = "preparing"
    evaluations: int = 0
    best_loss: float = math.inf
    best_pose: Pose | None = None


class _EngineJob:
    """One :func:`semcal_ros.optimize.calibrate` call, run by the node's :class:`_EngineWorker`;
    result or error kept."""

    def __init__(self, node: "CalibratorNode", handle: Any, inputs: Inputs,
                 request: Request) -> None:
        self.node, self.handle, self.inputs, self.request = node, handle, inputs, request
        self.result: Any = None
        self.error: Exception | None = None
        self.overlay: np.ndarray | None = None  # RGB, rendered after a result worth publishing
        self.overlay_error = ""
        self.done = threading.Event()
        self.stop = threading.Event()  # set once the goal is answered as cancelled / aborted
        self.release_on_exit = False
        self.started = time.perf_counter()

    def seconds(self) -> float:
        return time.perf_counter() - self.started

    def _should_stop(self) -> bool:
        # is_cancel_requested turns False again once the goal is answered as cancelled
        return self.stop.is_set() or self.handle.is_cancel_requested or not self.node.context.ok()

    def run(self) -> None:
        from semcal_ros.optimize import Cancelled, calibrate

        i, r = self.inputs, self.request
        try:
            self.result = calibrate(i.map_cloud, i.labels, i.camera, r.initial, r.params,
                                    self.node.mapping, r.seed, self.node.progress,
                                    self._should_stop)
            if not validation.result_problems(float(self.result.loss), r.params):
                try:  # here, not in an executor thread: the engine's thread does the heavy work
                    self.overlay = self.node.render_overlay(i, self.result.pose, r.params)
                except Exception as exc:  # noqa: BLE001 - a by-product; the result stands
                    self.overlay_error = f"{type(exc).__name__}: {exc}"
        except Cancelled as exc:
            self.error = exc
        except Exception as exc:  # noqa: BLE001 - reported as the goal's result
            if not isinstance(exc, ValueError):
                self.node.get_logger().error(traceback.format_exc())
            self.error = exc
        finally:
            self.done.set()
            self.node.job_ended(self)


class _EngineWorker:
    """The one thread that runs every goal's engine call, for the life of the node.

    A thread per goal made RSS grow from goal to goal (465 -> 667 MB over 25 cheap goals): glibc
    gives a new thread a malloc arena of its own, and each arena kept the high-water mark of the
    goal that used it. One long-lived thread reuses one arena, and after each goal the freed
    memory is handed back to the system (:func:`release_free_memory`).
    """

    def __init__(self) -> None:
        self._jobs: queue.Queue[_EngineJob | None] = queue.Queue()
        self.thread = threading.Thread(target=self._loop, name="calibrate", daemon=True)
        self.thread.start()

    def submit(self, job: _EngineJob) -> None:
        self._jobs.put(job)

    def close(self) -> None:
        self._jobs.put(None)

    def _loop(self) -> None:
        while (job := self._jobs.get()) is not None:
            job.run()
            job = None  # nothing of the goal (inputs, result, history) outlives it here
            release_free_memory()


class CalibratorNode(Node):
    def __init__(self) -> None:
        super().__init__("calibrator")
        self.opts = declare_and_read(self, CalibratorNodeParams())
        self.defaults = declare_and_read(self, CalibrationParams(), prefix="engine.")
        validation.check(validation.output_problems(self.opts.overlay_file,
                                                    "parameter 'overlay_file':"))
        self.mapping = LabelMapping.from_yaml(self.opts.label_mapping) \
            if self.opts.label_mapping else LabelMapping()
        self._lock = threading.Lock()
        self._map: LabelledCloud | None = None
        self._map_frame = self.opts.map_frame
        self._map_source = ""
        self._labels: np.ndarray | None = None
        self._labels_frame = ""
        self._camera = None
        self._rgb: np.ndarray | None = None
        self._run: _Run | None = None
        self._input_errors: dict[str, str] = {}
        self.last_rejection = ""
        self.last_result = ""
        if self.opts.map_file:
            self._load_map_file(self.opts.map_file)

        inputs = MutuallyExclusiveCallbackGroup()
        timers = MutuallyExclusiveCallbackGroup()
        overrides = qos.overridable()
        self.create_subscription(PointCloud2, "map", self._on_map, qos.latched(),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(Image, "camera/labels", self._on_labels, qos.sensor(2),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info,
                                 qos.sensor(2), callback_group=inputs,
                                 qos_overriding_options=overrides)
        self.create_subscription(Image, "camera/image_raw", self._on_image, qos.sensor(2),
                                 callback_group=inputs, qos_overriding_options=overrides)
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
            goal_callback=self._on_goal, cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self._feedback_handle = None
        self.engine = _EngineWorker()
        self.create_timer(self.opts.feedback_period, self._send_feedback, callback_group=timers)
        self.diagnostics = Diagnostics(self, self._report, self.opts.diagnostics_period,
                                       callback_group=timers)
        self.get_logger().info(
            f"ready: action '{self.resolve_topic_name('calibrate')}', map on "
            f"'{self.resolve_topic_name('map')}', labels on "
            f"'{self.resolve_topic_name('camera/labels')}'")

    # --- inputs ----------------------------------------------------------------------------
    def _load_map_file(self, path: str) -> None:
        from semcal_ros.io.ply import read_ply

        cloud = read_ply(path)
        with self._lock:
            self._map, self._map_source = cloud, path
        self.get_logger().info(f"map from {path}: {len(cloud)} points")

    def _convert(self, what: str, convert: Any, msg: Any) -> Any:
        """``convert(msg)``, or None with the reason logged once and kept for the diagnostics."""
        try:
            value = convert(msg)
        except ValueError as exc:
            if self._input_errors.get(what) != str(exc):
                self.get_logger().error(f"ignoring {what}: {exc}")
            self._input_errors[what] = str(exc)
            return None
        self._input_errors.pop(what, None)
        return value

    def _usable_map(self, msg: PointCloud2) -> LabelledCloud:
        """The map's finite points; ValueError (the held map is kept) when none is left."""
        raw = conv.pointcloud2_to_cloud(msg, require_label=True)
        cloud = raw.finite()
        if len(cloud) == 0:
            with self._lock:
                held = f"{len(self._map)} points" if self._map is not None else "none"
            what = "is empty" if len(raw) == 0 else \
                f"has no finite point ({len(raw)} points, all NaN or infinite)"
            raise ValueError(f"the map message {what}; keeping the map held ({held})")
        if len(cloud) < len(raw):
            self.get_logger().warning(f"map: {len(raw) - len(cloud)} of {len(raw)} points are "
                                      f"NaN or infinite and were dropped")
        return cloud

    def _on_map(self, msg: PointCloud2) -> None:
        cloud = self._convert("map", self._usable_map, msg)
        if cloud is None:
            return
        with self._lock:
            first = self._map is None or self._map_source != "topic"
            self._map, self._map_source = cloud, "topic"
            self._map_frame = msg.header.frame_id or self.opts.map_frame
        if first:
            self.get_logger().info(f"map received: {len(cloud)} points in '{self._map_frame}'")

    def _on_labels(self, msg: Image) -> None:
        labels = self._convert("label image", conv.image_to_labels, msg)
        if labels is not None:
            with self._lock:
                self._labels, self._labels_frame = labels, msg.header.frame_id

    def _on_camera_info(self, msg: CameraInfo) -> None:
        camera = self._convert("CameraInfo", conv.camera_info_to_model, msg)
        if camera is not None:
            with self._lock:
                self._camera = camera

    def _on_image(self, msg: Image) -> None:
        rgb = self._convert("camera image", conv.image_to_rgb, msg)
        if rgb is not None:
            with self._lock:
                self._rgb = rgb

    def inputs(self) -> Inputs:
        with self._lock:
            return Inputs(self._map, self._map_frame, self._labels, self._labels_frame,
                          self._camera, self.resolve_topic_name("map"),
                          self.resolve_topic_name("camera/labels"),
                          self.resolve_topic_name("camera/camera_info"))

    # --- the action ------------------------------------------------------------------------
    def _on_goal(self, goal: Any) -> GoalResponse:
        """Every goal is accepted: one that cannot run (another is running, or it is invalid)
        is aborted with the reason, which a rejection could not carry."""
        return GoalResponse.ACCEPT

    def _claim(self, goal_id: str) -> str:
        """Make ``goal_id`` the running goal; the reason when another one is running."""
        with self._lock:
            if self._run is not None:
                age = time.monotonic() - self._run.started
                self.last_rejection = (f"busy: goal {self._run.goal_id} has been running for "
                                       f"{age:.1f} s, now '{self._run.stage}' (one calibration "
                                       f"at a time)")
                return self.last_rejection
            self._run = _Run(goal_id, time.monotonic())
            self.last_rejection = ""
            return ""

    def _execute(self, handle: Any) -> Calibrate.Result:
        """Validate, hand the goal to the engine's thread, and answer it as soon as it is done
        or cancelled: a cancel is answered at once even while the engine is in a step
        that checks for it only at its end (it then stops there; until it has, new goals are
        refused as busy)."""
        goal_id = bytes(handle.goal_id.uuid).hex()[:8]
        busy = self._claim(goal_id)
        if busy:
            return self._finish(handle, "abort", busy)
        job = None
        try:
            inputs = self.inputs()
            try:
                request = goal_request(handle.request, inputs, self.defaults, self.opts.seed)
            except ValueError as exc:
                return self._finish(handle, "abort", f"invalid goal: {exc}")
            self.get_logger().info(
                f"goal {goal_id}: calibrating '{request.camera_frame}' against a map of "
                f"{len(inputs.map_cloud)} points from {np.round(request.initial.translation, 3)}")
            job = _EngineJob(self, handle, inputs, request)
            with self._lock:
                self._feedback_handle = handle
            self.engine.submit(job)
            while not job.done.wait(0.05):
                if handle.is_cancel_requested or not self.context.ok():
                    job.stop.set()
                    if handle.is_cancel_requested:
                        return self._cancelled(handle, job)
                    return self._finish(handle, "abort", "the calibrator is shutting down")
            return self._answer(handle, job, inputs, request)
        finally:
            with self._lock:
                self._feedback_handle = None
                if job is None or job.done.is_set():
                    self._run = None
                else:  # the engine stops at its next check, then frees the node
                    job.release_on_exit = True
                    if self._run is not None:
                        self._run.stage = "stopping (answered)"

    def _answer(self, handle: Any, job: _EngineJob, inputs: Inputs, request: Request
                ) -> Calibrate.Result:
        if job.error is not None:
            from semcal_ros.optimize import Cancelled

            exc = job.error
            if isinstance(exc, Cancelled):
                if handle.is_cancel_requested:
                    return self._cancelled(handle, job)
                return self._finish(handle, "abort", "the calibrator is shutting down")
            if isinstance(exc, ValueError):
                text = str(exc)
                if not text.startswith("calibration failed"):  # the engine may say it already
                    text = f"calibration failed: {text}"
                return self._finish(handle, "abort", text, seconds=job.seconds())
            return self._finish(handle, "abort", f"internal error: {type(exc).__name__}: {exc}",
                                seconds=job.seconds())
        result = job.result
        degenerate = validation.result_problems(float(result.loss), request.params)
        if degenerate:
            return self._finish(handle, "abort", f"calibration failed: {'; '.join(degenerate)}",
                                evaluations=int(result.evaluations),
                                seconds=float(result.seconds))
        transform = conv.transform_from_pose(result.pose, request.map_frame,
                                             request.camera_frame,
                                             self.get_clock().now().to_msg())
        self._publish_result(transform, job)
        rpy = result.pose.body_rpy_deg()
        message = (f"calibrated '{request.camera_frame}': t = "
                   f"[{', '.join(f'{v:.3f}' for v in result.pose.translation)}] m, rpy = "
                   f"[{', '.join(f'{v:.2f}' for v in rpy)}] deg, loss {result.loss:.5f}, "
                   f"{result.accepted}/{len(result.runs)} runs agree within "
                   f"{result.spread_translation_m * 100:.1f} cm / "
                   f"{result.spread_rotation_deg:.3f} deg, {result.seconds:.1f} s")
        return self._finish(handle, "succeed", message, transform=transform,
                            loss=float(result.loss),
                            spread_translation_m=float(result.spread_translation_m),
                            spread_rotation_deg=float(result.spread_rotation_deg),
                            evaluations=int(result.evaluations), seconds=float(result.seconds))

    def _cancelled(self, handle: Any, job: "_EngineJob") -> Calibrate.Result:
        with self._lock:
            evaluations = self._run.evaluations if self._run else 0
        seconds = job.seconds()
        return self._finish(handle, "canceled", f"cancelled after {seconds:.1f} s "
                            f"({evaluations} evaluations reported)", evaluations=evaluations,
                            seconds=seconds)

    def _finish(self, handle: Any, outcome: str, message: str, **fields: Any
                ) -> Calibrate.Result:
        result = Calibrate.Result(success=outcome == "succeed", message=message, **fields)
        getattr(handle, outcome)()
        self.last_result = message
        past = {"succeed": "succeeded", "abort": "aborted", "canceled": "cancelled"}[outcome]
        # rclpy binds a severity to each logging call site: one site per severity, never shared
        if outcome == "succeed":
            self.get_logger().info(f"goal {past}: {message}")
        else:
            self.get_logger().warning(f"goal {past}: {message}")
        return result

    def close(self) -> None:
        self.engine.close()

    def progress(self, p: Any) -> None:
        with self._lock:
            if self._run is not None:
                self._run.stage, self._run.evaluations = p.stage, p.evaluations
                self._run.best_loss, self._run.best_pose = p.best_loss, p.best_pose

    def job_ended(self, job: "_EngineJob") -> None:
        with self._lock:
            if job.release_on_exit:
                self._run = None

    def _publish_result(self, transform: Any, job: _EngineJob) -> None:
        self.result_pub.publish(transform)
        if self.tf_pub is not None:
            self.tf_pub.publish(TFMessage(transforms=[transform]))
        if job.overlay is None:
            self.get_logger().error(f"overlay failed: {job.overlay_error}")
            return
        camera = job.inputs.camera
        self.overlay_pub.publish(conv.numpy_to_image(
            np.ascontiguousarray(job.overlay, np.uint8), "rgb8",
            conv.make_header(camera.frame_id, transform.header.stamp)))
        if self.opts.overlay_file:
            from semcal_ros.io.files import write_rgb_image

            try:
                write_rgb_image(self.opts.overlay_file, job.overlay)
                self.get_logger().info(f"overlay written to {self.opts.overlay_file}")
            except OSError as exc:
                self.get_logger().error(f"overlay not written: {exc}")

    def render_overlay(self, inputs: Inputs, pose: Pose, params: CalibrationParams
                       ) -> np.ndarray:
        """The map rendered at ``pose`` over the camera image (the label colours without one),
        as the engine renders it with ``params``."""
        from semcal_ros.overlay import render_overlay
        from semcal_ros.problem import mapping_for

        with self._lock:
            rgb = self._rgb
        camera = inputs.camera
        if rgb is None or rgb.shape[:2] != (camera.height, camera.width):
            rgb = colorize(inputs.labels)  # no matching camera image: draw over the labels
        return render_overlay(inputs.map_cloud, camera, pose, rgb,
                              mapping_for(params, self.mapping), params=params.render)

    def _send_feedback(self) -> None:
        with self._lock:
            handle, run = self._feedback_handle, self._run
            if handle is None or run is None:
                return
            feedback = Calibrate.Feedback(stage=run.stage, evaluations=run.evaluations,
                                          best_loss=float(run.best_loss),
                                          elapsed_seconds=time.monotonic() - run.started)
            if run.best_pose is not None:
                feedback.best_pose = conv.pose_to_msg(run.best_pose)
        try:
            handle.publish_feedback(feedback)
        except Exception as exc:  # noqa: BLE001 - the goal may finish between lock and publish
            self.get_logger().debug(f"feedback not sent: {exc}")

    # --- diagnostics -----------------------------------------------------------------------
    def _report(self) -> tuple[Level, str, dict[str, Any]]:
        inputs = self.inputs()
        with self._lock:
            run = self._run
            values: dict[str, Any] = {
                "map_points": len(inputs.map_cloud) if inputs.map_cloud is not None else 0,
                "map_frame": inputs.map_frame,
                "map_source": self._map_source or "none",
                "label_image": "x".join(map(str, inputs.labels.shape[1::-1]))
                if inputs.labels is not None else "none",
                "camera_info": f"{inputs.camera.width}x{inputs.camera.height} "
                               f"'{inputs.camera.frame_id}'" if inputs.camera else "none",
                "state": f"running {run.goal_id} ({run.stage}, {run.evaluations} evaluations)"
                if run else "idle",
                "last_result": self.last_result or "none",
                "last_rejection": self.last_rejection or "none",
            }
            values.update({f"input_error.{k}": v for k, v in self._input_errors.items()})
        missing = input_problems("", inputs)
        if self._input_errors:
            return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in self._input_errors.items()), \
                values
        if missing:
            return Level.WARN, "; ".join(missing), values
        return Level.OK, "calibrating" if run else "ready", values


def main(args: list[str] | None = None) -> int:
    return run_node(CalibratorNode, threads=4, args=args)


if __name__ == "__main__":
    sys.exit(main())
