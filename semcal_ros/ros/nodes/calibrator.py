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

A moving rig (``rig_frames`` N > 1, :mod:`semcal_ros.ros.rig_pairs`): the node also takes the
lidar's labelled scans on ``labelled_points`` (the cloud_segmenter's output, lidar frame), pairs
each label image with the scan nearest in stamp (``rig_stamp_tolerance``; unpaired images are
counted in the diagnostics) and keeps the last N pairs per camera; a goal's initial pose is then
the camera's pose in the scans' frame, calibrated against all N frames at once (each frame's map
its own scan; :func:`semcal_ros.engine.calibration.calibrate_frames_and_draw`), one verdict, the
result published as always with the scans' frame as its parent.

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
from typing import Any, Callable

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from semcal_interfaces.action import Calibrate
from semcal_ros.engine import validation
from semcal_ros.engine.calibration import (Calibration, calibrate_and_draw,
                                           calibrate_frames_and_draw)
from semcal_ros.engine.frames import Frame
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
from semcal_ros.ros.camera_inputs import CameraInputs, CameraTopics, camera_topics
from semcal_ros.ros.diagnostics import Diagnostics
from semcal_ros.ros.engine_job import EngineJob, GoalRunner, GoalState
from semcal_ros.ros.goal_answers import GoalAnswers
from semcal_ros.ros.label_window import WindowedCameraInputs, window_labels
from semcal_ros.ros.map_intake import MapIntake
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.result_publisher import DEFAULT_PUBLISH_VERDICTS, ResultPublisher
from semcal_ros.ros.rig_pairs import (SCANS_TOPIC, Pair, RigCameraInputs, RigPairs, ScanBuffer,
                                      frame_map, on_scan_message, rig_goal_request)
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
    # a moving rig: calibrate the camera's pose in the lidar frame against its last N label
    # images, each paired with the labelled scan (labelled_points) nearest in stamp
    # (semcal_ros.ros.rig_pairs); 1 = the map and the newest label image, as without it
    rig_frames: int = 1
    rig_stamp_tolerance: float = 0.05  # s: a label image and its scan at most this far apart
    rig_scans_held: int = 10  # labelled scans kept for pairing (label images that lag behind)

    def __post_init__(self) -> None:
        if self.label_window < 1:
            raise ValueError(f"label_window must be >= 1 frames, got {self.label_window}")
        if self.rig_frames < 1:
            raise ValueError(f"rig_frames must be >= 1 frames, got {self.rig_frames}")
        if not self.rig_stamp_tolerance > 0:
            raise ValueError(f"rig_stamp_tolerance must be > 0 s, got {self.rig_stamp_tolerance}")
        if self.rig_scans_held < 1:
            raise ValueError(f"rig_scans_held must be >= 1 scans, got {self.rig_scans_held}")
        if self.rig_frames > 1 and self.label_window > 1:
            raise ValueError(f"label_window {self.label_window} (a static camera) and rig_frames "
                             f"{self.rig_frames} (a moving rig) exclude each other: set one to 1")
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
        self.rig = self.opts.rig_frames > 1
        self.scans = ScanBuffer(self.opts.rig_scans_held)
        self.cameras: dict[str, CameraInputs] = {
            t.name: self._camera_inputs(t) for t in camera_topics(self.opts.cameras)}
        if self.opts.map_file:
            self.maps.load_file(self.opts.map_file)

        inputs = MutuallyExclusiveCallbackGroup()
        timers = MutuallyExclusiveCallbackGroup()
        overrides = qos.overridable()
        self.create_subscription(PointCloud2, "map", self.maps.on_message, qos.latched(),
                                 callback_group=inputs, qos_overriding_options=overrides)
        for camera in self.cameras.values():
            camera.subscribe(self, inputs, overrides)
        if self.rig:
            rig_cameras = [c for c in self.cameras.values() if isinstance(c, RigCameraInputs)]
            scans_topic = self.resolve_topic_name(SCANS_TOPIC)
            self.create_subscription(
                PointCloud2, SCANS_TOPIC,
                lambda msg: on_scan_message(msg, self.scans, rig_cameras,
                                            self.get_logger().error, scans_topic),
                qos.sensor(5), callback_group=inputs, qos_overriding_options=overrides)
        self.results = ResultPublisher(self, self.opts.publish_tf_static, self.opts.overlay_file,
                                       overrides, self.opts.publish_verdicts)
        self.action = ActionServer(
            self, Calibrate, "calibrate", execute_callback=self._execute,
            goal_callback=lambda _: GoalResponse.ACCEPT,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.goals = GoalRunner(self, self.opts.feedback_period, self._feedback, timers,
                                worker_name="calibrate")
        self.status = CalibratorStatus(
            self.cameras, self.goals, self.maps,
            (lambda camera: camera.problems()) if self.rig
            else (lambda camera: input_problems("", self.inputs(camera))),
            self.resolve_topic_name("map"), needs_map=not self.rig)
        self.answers = GoalAnswers(self, self.status)
        self.diagnostics = Diagnostics(
            self, self.status.report, self.opts.diagnostics_period, callback_group=timers,
            parts=self.status.camera_reports if self.status.named else None)
        labels = ", ".join(f"'{self.resolve_topic_name(c.topics.labels)}'"
                           for c in self.cameras.values())
        self.get_logger().info(
            f"ready: action '{self.resolve_topic_name('calibrate')}', map on "
            f"'{self.resolve_topic_name('map')}', labels on {labels}"
            + (f"; a rig of {self.opts.rig_frames} frames: labelled scans on "
               f"'{self.resolve_topic_name(SCANS_TOPIC)}'" if self.rig else ""))

    def _camera_inputs(self, topics: CameraTopics) -> CameraInputs:
        """A camera's input cache: with a label window, or with a rig's pairs."""
        log = self.get_logger()
        common = (topics, log.error, self.resolve_topic_name, self.opts.image_transport,
                  self.opts.labels_transport, log.warning)
        if self.rig:
            return RigCameraInputs(*common, rig=RigPairs(self.opts.rig_frames,
                                                         self.opts.rig_stamp_tolerance,
                                                         self.scans))
        return WindowedCameraInputs(*common, window=self.opts.label_window)

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
            goal = handle.request
            if frame != goal.camera_frame_id:
                goal = copy.copy(goal)
                goal.camera_frame_id = frame
            try:
                request, work, against = self._plan(goal, camera, state)
            except InputError as exc:
                return self.answers.finish(handle, "abort", f"invalid goal: {exc}")
            ahead = sum(1 for k, s in self.goals.states().items()
                        if k != camera.name and s.submitted)
            self.get_logger().info(
                f"goal {goal_id}: calibrating '{request.camera_frame}' against {against} from "
                f"{np.round(request.initial.translation, 3)}"
                + (f" (queued behind {ahead} goal{'s' * (ahead > 1)})" if ahead else ""))
            job = EngineJob(work, stop_also=lambda: not self.context.ok(),
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

    def _plan(self, goal: Any, camera: CameraInputs, state: GoalState
              ) -> tuple[Request, Callable[[EngineJob], Calibration], str]:
        """The goal checked (InputError naming every problem), the engine work it asks for,
        and what it calibrates against (for the log)."""
        if isinstance(camera, RigCameraInputs):
            request, pairs = rig_goal_request(goal, camera, self.defaults, self.opts.seed)
            points = ", ".join(str(len(p.scan.cloud)) for p in pairs)
            return (request, lambda j: self._calibrate_rig(j, state, pairs, request, camera),
                    f"{len(pairs)} frames of the rig in '{request.map_frame}' (scans of "
                    f"{points} points)")
        inputs = self.inputs(camera)
        request = goal_request(goal, inputs, self.defaults, self.opts.seed)
        return (request, lambda j: self._calibrate(j, state, inputs, request, camera),
                f"a map of {inputs.map.points} points")

    def _calibrate_rig(self, job: EngineJob, state: GoalState, pairs: list[Pair],
                       request: Request, camera: CameraInputs) -> Calibration:
        """(engine thread) One pose in the scans' frame over every pair, each frame's map its
        own scan (the engine's FrameSet); the overlay is the newest frame's, over the camera's
        newest image."""
        snap = camera.snapshot()
        frames = [Frame(frame_map(p.scan.cloud, p.scan.stamp), p.labels, snap.camera,
                        request.params, background=snap.rgb if k == len(pairs) - 1 else None,
                        name=p.name)
                  for k, p in enumerate(pairs)]
        self.get_logger().info(
            f"goal for '{request.camera_frame}': one-scan maps of "
            f"{', '.join(str(len(f.map_cloud)) for f in frames)} points")
        calibration = calibrate_frames_and_draw(
            frames, request.initial, self.mapping, seed=request.seed,
            progress=lambda p: self.goals.progress(state, p), should_stop=job.should_stop)
        if calibration.overlays:
            calibration.overlay = calibration.overlays[-1]
        for check in calibration.frames:
            self.get_logger().info(
                f"goal for '{request.camera_frame}': {check.name}: loss {check.loss:.5f}, "
                f"agreement {check.agreement * 100:.1f} %, coverage {check.coverage * 100:.1f} %")
        return calibration

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
