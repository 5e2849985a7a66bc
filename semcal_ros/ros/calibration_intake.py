"""Where the calibration monitor learns each camera's calibration: a pose file at start,
``calibration/transform`` and ``/tf_static`` (the calibrator publishes both); the newest wins.

A transform is matched to a camera by its child frame (the camera's CameraInfo frame, or its
name); the single unnamed camera takes an unframed one before its CameraInfo came (the
calibrator's usual frame). ``/tf_static`` is latched and comes once, possibly before a camera's
CameraInfo says which frame is its own, so its transforms are kept and matched again before every
check round (:meth:`CalibrationIntake.match_pending`). An unusable transform (another frame than
the map's, NaN, a quaternion that is not unit) is refused with one line naming it.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Mapping

import numpy as np
from geometry_msgs.msg import TransformStamped

from semcal_ros.engine.pose import Pose
from semcal_ros.errors import InputError
from semcal_ros.ros import conversions as conv


def calibration_pose(msg: TransformStamped, map_frame: str) -> Pose:
    """The camera pose a transform gives, or :class:`InputError` saying why it is unusable."""
    if msg.header.frame_id and msg.header.frame_id != map_frame:
        raise InputError(f"it is in '{msg.header.frame_id}', the map in '{map_frame}'")
    tr, rot = msg.transform.translation, msg.transform.rotation
    q = np.array([rot.x, rot.y, rot.z, rot.w])
    if not (np.all(np.isfinite([tr.x, tr.y, tr.z])) and np.all(np.isfinite(q))
            and abs(np.linalg.norm(q) - 1.0) < 1e-3):
        raise InputError("not a finite pose with a unit quaternion")
    return conv.pose_from_transform(msg)


class CalibrationIntake:
    """Turns files and transforms into ``take(name, pose, source)`` calls, one per camera
    (``inputs``: camera name -> :class:`~semcal_ros.ros.camera_inputs.CameraInputs`)."""

    def __init__(self, inputs: Mapping[str, Any], map_frame: Callable[[], str],
                 take: Callable[[str, Pose, str], None], logger: Any) -> None:
        self.inputs, self.map_frame, self.take, self.logger = inputs, map_frame, take, logger
        self._lock = threading.Lock()
        self._tf_static: dict[str, TransformStamped] = {}

    def load_files(self, pattern: str) -> None:
        """``pattern`` with ``{name}`` replaced by each camera's name ("camera" if unnamed)."""
        from semcal_ros.io.files import read_pose

        for name, inputs in self.inputs.items():
            path = pattern.replace("{name}", name or "camera")
            try:
                self.take(name, read_pose(path), f"file {path}")
            except (ValueError, OSError) as exc:
                self.logger.error(f"ignoring calibration_file for {inputs.topics.label}: {exc}")

    def camera_of(self, frame_id: str, unframed: bool = True) -> str | None:
        """The name of the camera ``frame_id`` belongs to (None: no monitored camera)."""
        for name, inputs in self.inputs.items():
            if inputs.answers_to(frame_id):
                return name
        if unframed and len(self.inputs) == 1 and "" in self.inputs \
                and not self.inputs[""].snapshot().frame_id:
            return ""
        return None

    def on_transform(self, msg: TransformStamped) -> None:
        self.take_transform(msg, "calibration/transform")

    def on_tf_static(self, msg: Any) -> None:
        frame = self.map_frame()
        with self._lock:
            self._tf_static = {tf.child_frame_id: tf for tf in msg.transforms
                               if tf.header.frame_id == frame}
        self.match_pending()

    def match_pending(self) -> None:
        """Match the kept ``/tf_static`` transforms again (a camera's frame may be known now)."""
        with self._lock:
            pending = list(self._tf_static.values())
        for tf in pending:
            self.take_transform(tf, "/tf_static", quiet=True)

    def take_transform(self, msg: TransformStamped, source: str, quiet: bool = False) -> None:
        name = self.camera_of(msg.child_frame_id, unframed=not quiet)
        if name is None:
            if not quiet:
                self.logger.warning(f"ignoring {source}: no monitored camera has frame "
                                    f"'{msg.child_frame_id}'")
            return
        try:
            pose = calibration_pose(msg, self.map_frame())
        except InputError as exc:
            self.logger.error(f"ignoring {source} for '{msg.child_frame_id}': {exc}")
            return
        self.take(name, pose, source)


__all__ = ["CalibrationIntake", "calibration_pose"]
