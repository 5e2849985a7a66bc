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
uncertainty) and, when its verdict is one of ``publish_verdicts`` (default good and
inconclusive: a failed result never replaces the transform held), to
``calibration/transform`` (TransformStamped, transient local) and to ``/tf_static`` (one
TFMessage holding the transforms of every camera calibrated so far, as tf2's static broadcaster
does); every result, as a picture of the map rendered at the result over the camera image with
the verdict drawn on it, to ``calibration/overlay``. /diagnostics carries the node's status and,
with named cameras, one status per camera (``calibrator/<name>``): its inputs, its goal and the
verdict of its last result (WARN inconclusive, ERROR failed).

The node is wiring. The calibration and its overlay are the engine's
(:func:`semcal_ros.engine.calibration.calibrate_and_draw`, as ``semcal calibrate`` runs them);
the goal's checks and routing :mod:`semcal_ros.ros.calibrate_goal`; the answers
:mod:`semcal_ros.ros.goal_answers` (by error type); the texts and diagnostics
:mod:`semcal_ros.ros.calibrator_status`; the map :mod:`semcal_ros.ros.map_intake`; the
published result :mod:`semcal_ros.ros.result_publisher`.
"""

from __future__ import annotations

import copy
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from semcal_interfaces.action import Calibrate
from semcal_ros.engine import validation
from semcal_ros.engine.calibration import Calibration, calibrate_and_draw
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.problem import mapping_for
from semcal_ros.engine.quality import VERDICTS
from semcal_ros.errors import InputError
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.calibrate_goal import (Inputs, Request, camera_for_goal, goal_request,
                                           input_problems)
from semcal_ros.ros.calibrator_status import CalibratorStatus
from semcal_ros.ros.camera_inputs import CameraInputs, camera_topics
from semcal_ros.ros.diagnostics import Diagnostics
from semcal_ros.ros.engine_job import EngineJob, GoalRunner, GoalState
from semcal_ros.ros.goal_answers import GoalAnswers
from semcal_ros.ros.label_window import WindowedCameraInputs, window_labels
from semcal_ros.ros.map_intake import MapIntake
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.result_publisher import DEFAULT_PUBLISH_VERDICTS, ResultPublisher
from semcal_ros.ros.runtime import run_node

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
    # verdicts whose result is published (calibration/transform, /tf_static); a failed one is
    # not by default: the transform held before stays, the action result carries it
    publish_verdicts: tuple[str, ...] = DEFAULT_PUBLISH_VERDICTS
    overlay_file: str = ""  # also write the overlay picture here (PNG) after each success
    image_transport: str = "raw"  # camera image: raw, or compressed (<image_raw>/compressed)
    labels_transport: str = "raw"  # label image: raw, or compressed (PNG only; JPEG refused)
    # a static camera: calibrate against the per-pixel fusion of its last N label images
    # (semcal_ros.ros.label_window); 1 = the newest image only
    label_window: int = 1

    def __post_init__(self) -> None:
        if self.label_window < 1:
            raise ValueError(f"label_window must be >= 1 frames, got {self.label_window}")
        if not 0 < self.feedback_period <= 1.0:
            raise ValueError("feedback_period must be in (0, 1] s (feedback at least once a "
                             f"second), got {self.feedback_period}")
        camera_topics(self.cameras)  # raises naming a bad or repeated name
        unknown = [v for v in self.publish_verdicts if v not in VERDICTS]
        if unknown:
            raise ValueError(f"parameter 'publish_verdicts': {', '.join(map(repr, unknown))} "
                             f"is not a verdict (choose from {', '.join(VERDICTS)})")


class CalibratorNode(Node):
    def __init__(self) -> None:
        super().__init__("calibrator")
        self.opts = declare_and_read(self, CalibratorNodeParams())
        self.defaults = declare_and_read(self, CalibrationParams(), prefix="engine.")
        validation.check(validation.output_problems(self.opts.overlay_file,
                                                    "parameter 'overlay_file':"))
        self.mapping = LabelMapping.from_yaml(self.opts.label_mapping) \
            if self.opts.label_mapping else LabelMapping()
        # the alignment every goal's Problem uses (goals cannot change labels.merge), so the
        # map is prepared with it once
        self.maps = MapIntake(mapping_for(self.defaults, self.mapping), self.opts.map_frame,
                              self.get_logger())
        self.cameras: dict[str, CameraInputs] = {
            t.name: WindowedCameraInputs(t, self.get_logger().error, self.resolve_topic_name,
                                         self.opts.image_transport, self.opts.labels_transport,
                                         self.get_logger().warning,
                                         window=self.opts.label_window)
            for t in camera_topics(self.opts.cameras)}
        if self.opts.map_file:
            self.maps.load_file(self.opts.map_file)

        inputs = MutuallyExclusiveCallbackGroup()
        timers = MutuallyExclusiveCallbackGroup()
        overrides = qos.overridable()
        self.create_subscription(PointCloud2, "map", self.maps.on_message, qos.latched(),
                                 callback_group=inputs, qos_overriding_options=overrides)
        for camera in self.cameras.values():
            camera.subscribe(self, inputs, overrides)
        self.results = ResultPublisher(self, self.opts.publish_tf_static, self.opts.overlay_file,
                                       overrides, self.opts.publish_verdicts)
        self.action = ActionServer(
            self, Calibrate, "calibrate", execute_callback=self._execute,
            goal_callback=lambda _: GoalResponse.ACCEPT,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.goals = GoalRunner(self, self.opts.feedback_period, self._feedback, timers,
                                worker_name="calibrate")
        self.status = CalibratorStatus(self.cameras, self.goals, self.maps,
                                       lambda camera: input_problems("", self.inputs(camera)),
                                       self.resolve_topic_name("map"))
        self.answers = GoalAnswers(self, self.status)
        self.diagnostics = Diagnostics(
            self, self.status.report, self.opts.diagnostics_period, callback_group=timers,
            parts=self.status.camera_reports if self.status.named else None)
        labels = ", ".join(f"'{self.resolve_topic_name(c.topics.labels)}'"
                           for c in self.cameras.values())
        self.get_logger().info(
            f"ready: action '{self.resolve_topic_name('calibrate')}', map on "
            f"'{self.resolve_topic_name('map')}', labels on {labels}")

    @property
    def last_result(self) -> str:
        return self.status.last_result

    def inputs(self, camera: CameraInputs) -> Inputs:
        snap = camera.snapshot()
        return Inputs(self.maps.held, self.maps.frame, snap.labels, snap.labels_frame,
                      snap.camera, self.resolve_topic_name("map"),
                      self.resolve_topic_name(camera.topics.labels),
                      self.resolve_topic_name(camera.topics.camera_info))

    # --- the action ------------------------------------------------------------------------
    def _execute(self, handle: Any) -> Calibrate.Result:
        """Validate, queue the goal on the engine thread, and answer it as soon as it is done
        or cancelled (see :mod:`semcal_ros.ros.engine_job`)."""
        goal_id = bytes(handle.goal_id.uuid).hex()[:8]
        camera, frame = camera_for_goal(self.cameras, handle.request.camera_frame_id)
        if camera is None:
            return self.answers.finish(handle, "abort", f"invalid goal: {frame}")
        state = self.goals.claim(camera.name, goal_id, handle)
        if isinstance(state, str):
            return self.answers.finish(handle, "abort", state)
        job = None
        try:
            inputs = self.inputs(camera)
            goal = handle.request
            if frame != goal.camera_frame_id:
                goal = copy.copy(goal)
                goal.camera_frame_id = frame
            try:
                request = goal_request(goal, inputs, self.defaults, self.opts.seed)
            except InputError as exc:
                return self.answers.finish(handle, "abort", f"invalid goal: {exc}")
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
                return self.answers.cancelled(handle, job, state)
            if outcome == "shutdown":
                return self.answers.finish(handle, "abort", "the calibrator is shutting down")
            transform, withheld = self._publish(job.result, request) if job.error is None \
                else (None, "")
            return self.answers.ended(handle, job, camera.name, request.camera_frame, transform,
                                      withheld)
        finally:
            self.goals.release(state, job)

    def _calibrate(self, job: EngineJob, state: GoalState, inputs: Inputs, request: Request,
                   camera: CameraInputs) -> Calibration:
        """(engine thread) The engine's calibration and overlay on the shared prepared map,
        drawn over the camera's newest image (the label colours without a matching one);
        against the fusion of the camera's last label images with ``label_window`` > 1."""
        labels, fused = window_labels(camera, inputs.labels)
        if fused:
            self.get_logger().info(f"goal for '{request.camera_frame}': {fused}")
        return calibrate_and_draw(
            None, labels, inputs.camera, request.initial, request.params, self.mapping,
            prepared=inputs.map.prepared, background=camera.snapshot().rgb,
            seed=request.seed, progress=lambda p: self.goals.progress(state, p),
            should_stop=job.should_stop)

    def _publish(self, calibration: Calibration, request: Request
                 ) -> tuple[TransformStamped, str]:
        """The result as a transform, published if its verdict is in ``publish_verdicts``; and
        why it was not ("" when it was)."""
        transform = conv.transform_from_pose(calibration.result.pose, request.map_frame,
                                             request.camera_frame,
                                             self.get_clock().now().to_msg())
        quality = calibration.result.quality
        verdict = quality.verdict if quality is not None else None
        self.results.publish(transform, calibration.overlay, calibration.overlay_error, verdict)
        return transform, self.results.withheld(verdict)

    def _feedback(self, state: GoalState) -> Calibrate.Feedback:
        feedback = Calibrate.Feedback(stage=state.stage, evaluations=state.evaluations,
                                      best_loss=float(state.best_loss),
                                      elapsed_seconds=time.monotonic() - state.accepted)
        if state.best_pose is not None:
            feedback.best_pose = conv.pose_to_msg(state.best_pose)
        return feedback

    def close(self) -> None:
        self.goals.close()


def main(args: list[str] | None = None) -> int:
    return run_node(CalibratorNode, threads=lambda node: BASE_THREADS + len(node.cameras),
                    args=args)


if __name__ == "__main__":
    sys.exit(main())
