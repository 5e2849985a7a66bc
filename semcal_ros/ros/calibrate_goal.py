"""The Calibrate action's goal checked and turned into the engine's inputs.

Kept apart from the node so that what makes a goal invalid, and what each goal field does to the
:class:`~semcal_ros.engine.params.CalibrationParams`, can be read (and tested) without DDS. Every problem
is named in one message, because the caller only sees the action result's text.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from semcal_ros.engine import validation
from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.config import apply_flat
from semcal_ros.engine.loss import LOSS_KINDS
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.errors import InputError
from semcal_ros.ros.held_map import HeldMap

ROLL_CHOICES = {0: None, 1: False, 2: True}  # ROLL_DEFAULT, ROLL_FIXED, ROLL_FREE
YAW_SEARCH_CHOICES = {0: None, 1: False, 2: True}
LOSS_CHOICES = ("", *LOSS_KINDS)  # "" = the node's engine.loss.kind


@dataclass
class Inputs:
    """What the calibrator node holds when a goal arrives (None: not received yet)."""

    map: HeldMap | None  # prepared once per map, shared by every goal and camera
    map_frame: str
    labels: np.ndarray | None
    labels_frame: str
    camera: CameraModel | None
    map_topic: str = "map"
    labels_topic: str = "camera/labels"
    camera_info_topic: str = "camera/camera_info"


@dataclass
class Request:
    """A valid goal: where to start, with which parameters, for which frames."""

    initial: Pose
    params: CalibrationParams
    seed: int | None
    map_frame: str
    camera_frame: str


def _vector(v: Any) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def goal_problems(goal: Any, inputs: Inputs) -> list[str]:
    """Everything wrong with ``goal`` given ``inputs``; empty when it can run. The checks are
    :mod:`semcal_ros.engine.validation`'s, shared with ``semcal calibrate``."""
    frame = validation.frame_problems(goal.initial_pose.header.frame_id, inputs.map_frame)
    return field_problems(goal, frame) + input_problems(goal.camera_frame_id, inputs)


def field_problems(goal: Any, frame: list[str] | None = None) -> list[str]:
    """What is wrong with the goal's own fields (pose, bounds, options), whatever it runs on;
    ``frame``: the problems of its pose's frame, listed after the pose's own."""
    pose = goal.initial_pose.pose
    position = [pose.position.x, pose.position.y, pose.position.z]
    orientation = [pose.orientation.x, pose.orientation.y, pose.orientation.z,
                   pose.orientation.w]
    problems = validation.pose_problems(position, orientation, "initial_pose") + (frame or [])
    problems += validation.bound_problems(_vector(goal.bound_translation_m),
                                          _vector(goal.bound_rpy_deg))
    if goal.verification_starts < -1:
        problems.append(f"verification_starts must be >= 0 (-1 = node default), "
                        f"got {goal.verification_starts}")
    if goal.roll not in ROLL_CHOICES:
        problems.append(f"roll must be ROLL_DEFAULT, ROLL_FIXED or ROLL_FREE (0-2), got {goal.roll}")
    if goal.yaw_search not in YAW_SEARCH_CHOICES:
        problems.append(f"yaw_search must be 0-2, got {goal.yaw_search}")
    if goal.loss not in LOSS_CHOICES:
        kinds = ", ".join(f"'{k}'" for k in LOSS_KINDS)
        problems.append(f"loss must be {kinds} or '' (node default), got '{goal.loss}'")
    return problems


def input_problems(camera_frame_id: str, inputs: Inputs) -> list[str]:
    """Missing or inconsistent map / label image / CameraInfo."""
    problems = []
    if inputs.map is None:
        problems.append(f"no map received yet (topic '{inputs.map_topic}')")
    elif len(inputs.map) == 0:
        problems.append(f"the map on '{inputs.map_topic}' is empty")
    return problems + camera_problems(camera_frame_id, inputs.labels, inputs.labels_frame,
                                      inputs.camera, inputs.labels_topic,
                                      inputs.camera_info_topic)


def camera_problems(camera_frame_id: str, labels: np.ndarray | None, labels_frame: str,
                    camera: CameraModel | None, labels_topic: str = "camera/labels",
                    camera_info_topic: str = "camera/camera_info") -> list[str]:
    """Missing or inconsistent label image / CameraInfo of one camera (``camera_frame_id``
    empty: any frame)."""
    problems = []
    if labels is None:
        problems.append(f"no label image received yet (topic '{labels_topic}')")
    if camera is None:
        problems.append(f"no CameraInfo received yet (topic '{camera_info_topic}')")
    if labels is not None and camera is not None:
        h, w = labels.shape[:2]
        if (w, h) != (camera.width, camera.height):
            problems.append(f"label image is {w}x{h} but CameraInfo says "
                            f"{camera.width}x{camera.height}")
    if camera_frame_id:
        for what, frame in (("CameraInfo", camera.frame_id if camera else None),
                            ("label image", labels_frame if labels is not None else None)):
            if frame is not None and frame != camera_frame_id:
                problems.append(f"goal asks for camera '{camera_frame_id}' but the {what} is "
                                f"from '{frame}'")
    return problems


def goal_params(goal: Any, defaults: CalibrationParams) -> CalibrationParams:
    """``defaults`` with the goal's bounds and options applied (0 / -1 / '' keep defaults)."""
    search = defaults.search
    flat: dict[str, Any] = {}
    bt = _vector(goal.bound_translation_m)
    if any(v > 0 for v in bt):
        flat["search.bound_xyz"] = tuple(v if v > 0 else d for v, d in zip(bt, search.bound_xyz))
    roll, pitch, yaw = _vector(goal.bound_rpy_deg)
    for key, value in (("bound_roll_deg", roll), ("bound_pitch_deg", pitch),
                       ("bound_yaw_deg", yaw)):
        if value > 0:
            flat[f"search.{key}"] = value
    if ROLL_CHOICES.get(goal.roll) is not None:
        flat["search.free_roll"] = ROLL_CHOICES[goal.roll]
    if YAW_SEARCH_CHOICES.get(goal.yaw_search) is not None:
        flat["search.yaw_search"] = YAW_SEARCH_CHOICES[goal.yaw_search]
    if goal.verification_starts >= 0:
        flat["verification.starts"] = int(goal.verification_starts)
    if goal.loss:
        flat["loss.kind"] = goal.loss
    return apply_flat(defaults, flat)


def goal_request(goal: Any, inputs: Inputs, defaults: CalibrationParams,
                 default_seed: int) -> Request:
    """A runnable request, or :class:`InputError` listing every problem of the goal."""
    problems = goal_problems(goal, inputs)
    if problems:
        raise InputError("; ".join(problems))
    return checked_request(goal, defaults, default_seed, inputs.map_frame, inputs.map.bounds,
                           inputs.camera)


def checked_request(goal: Any, defaults: CalibrationParams, default_seed: int, map_frame: str,
                    bounds: Any, camera: CameraModel) -> Request:
    """The request of a goal whose problems were checked: its pose, parameters and seed; the
    initial pose checked against the ``bounds`` of what it is to see (InputError)."""
    p = goal.initial_pose.pose
    initial = Pose(np.array([p.position.x, p.position.y, p.position.z]),
                   np.array([p.orientation.x, p.orientation.y, p.orientation.z,
                             p.orientation.w]))
    params = goal_params(goal, defaults)
    validation.check(validation.reach_problems(initial.translation, bounds, params))
    camera_frame = goal.camera_frame_id or camera.frame_id or "camera_optical"
    seed = int(goal.seed) if goal.seed >= 0 else default_seed
    return Request(initial, params, seed if seed >= 0 else None, map_frame, camera_frame)


def camera_for_goal(cameras: Mapping[str, Any], camera_frame_id: str) -> tuple[Any | None, str]:
    """The camera (of ``cameras``: name -> CameraInputs) a goal's ``camera_frame_id`` means,
    and the frame id to check its inputs against; or None and the reason. A name selects its
    camera whatever its frame; the single unnamed camera takes any (its inputs' check then
    names a wrong frame)."""
    if len(cameras) == 1 and "" in cameras:
        return cameras[""], camera_frame_id
    served = ", ".join(f"'{c.name}'" + (f" ({c.snapshot().frame_id})"
                                        if c.snapshot().frame_id else "")
                       for c in cameras.values())
    if not camera_frame_id:
        if len(cameras) == 1:
            return next(iter(cameras.values())), ""
        return None, (f"camera_frame_id is empty but this calibrator serves cameras "
                      f"{served}: name one")
    if camera_frame_id in cameras:
        return cameras[camera_frame_id], ""  # by name: any frame id of that camera
    for camera in cameras.values():
        if camera.answers_to(camera_frame_id):
            return camera, camera_frame_id
    return None, f"unknown camera '{camera_frame_id}': this calibrator serves {served}"
