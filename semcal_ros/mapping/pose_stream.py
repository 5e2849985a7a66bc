"""Poses as rigid 4x4 transforms, and a time-stamped pose stream interpolated at scan times.

A live lidar scan carries a time stamp but no pose; the pose comes from odometry or localisation
at its own rate. :class:`PoseStream` keeps a bounded window of those poses and answers "where
was the sensor at time t" by interpolation (linear translation, slerp rotation), refusing times
it does not cover, because extrapolating a moving vehicle's pose smears the map.
"""

from __future__ import annotations

from bisect import bisect_left
from collections import deque
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def as_matrix(pose: Any, what: str = "pose") -> np.ndarray:
    """A rigid 4x4 transform from a 4x4 array or an object with ``rotation`` and ``translation``
    (e.g. :class:`semcal_ros.engine.pose.Pose`); refuses non-finite or non-rigid input."""
    if hasattr(pose, "rotation") and hasattr(pose, "translation"):
        matrix = np.eye(4)
        matrix[:3, :3] = np.asarray(pose.rotation, float)
        matrix[:3, 3] = np.asarray(pose.translation, float)
    else:
        matrix = np.asarray(pose, dtype=float)
        if matrix.shape != (4, 4):
            raise ValueError(f"{what} must be a 4x4 transform, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{what} contains NaN or infinite values")
    r = matrix[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-4 or np.linalg.det(r) < 0:
        raise ValueError(f"{what} has a rotation part that is not a rotation")
    if np.abs(matrix[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f"{what}: last row must be [0, 0, 0, 1]")
    return matrix


class PoseNotCovered(ValueError):
    """A requested time lies outside the poses received."""


class PoseStream:
    """Time-stamped poses in arrival order; :meth:`at` interpolates between neighbours.

    ``tolerance`` seconds beyond either end are answered with the end pose (stamps of different
    sensors rarely match to the microsecond). At most ``max_poses`` are kept (oldest dropped), so
    a long drive does not grow memory.
    """

    def __init__(self, tolerance: float = 0.02, max_poses: int = 10000) -> None:
        self.tolerance = float(tolerance)
        self._stamps: deque[float] = deque(maxlen=max_poses)
        self._poses: deque[np.ndarray] = deque(maxlen=max_poses)

    def __len__(self) -> int:
        return len(self._stamps)

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()

    def add(self, stamp: float, pose: Any) -> None:
        """Append a pose; stamps must not go backwards (a reordered stream is an error)."""
        matrix = as_matrix(pose)
        stamp = float(stamp)
        if not np.isfinite(stamp):
            raise ValueError("pose stamp is not finite")
        if self._stamps and stamp < self._stamps[-1]:
            raise ValueError(f"pose at {stamp:.6f} s is older than the previous one "
                             f"({self._stamps[-1]:.6f} s)")
        if self._stamps and stamp == self._stamps[-1]:
            self._poses[-1] = matrix
            return
        self._stamps.append(stamp)
        self._poses.append(matrix)

    def span(self) -> tuple[float, float] | None:
        return (self._stamps[0], self._stamps[-1]) if self._stamps else None

    def at(self, stamp: float) -> np.ndarray:
        """The pose at ``stamp``; :class:`PoseNotCovered` if the stream does not cover it."""
        if not self._stamps:
            raise PoseNotCovered(f"no pose received yet for the scan at {stamp:.6f} s")
        first, last = self._stamps[0], self._stamps[-1]
        if stamp < first - self.tolerance or stamp > last + self.tolerance:
            raise PoseNotCovered(f"no pose covers the scan at {stamp:.6f} s "
                                 f"(poses cover {first:.6f} .. {last:.6f} s)")
        if stamp <= first:
            return self._poses[0].copy()
        if stamp >= last:
            return self._poses[-1].copy()
        stamps = list(self._stamps)
        j = bisect_left(stamps, stamp)
        if stamps[j] == stamp:
            return self._poses[j].copy()
        a, b = self._poses[j - 1], self._poses[j]
        f = (stamp - stamps[j - 1]) / (stamps[j] - stamps[j - 1])
        out = np.eye(4)
        out[:3, 3] = (1 - f) * a[:3, 3] + f * b[:3, 3]
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix([a[:3, :3], b[:3, :3]]))
        out[:3, :3] = slerp([f]).as_matrix()[0]
        return out
