"""Camera pose conventions, all in one place.

A pose is the camera's optical frame (REP-103 ``*_optical``: z forward, x right, y down) in the map
frame: ``translation`` is the camera centre, ``quaternion`` (x, y, z, w) its orientation. People and
priors speak in the body frame instead (x forward, y left, z up; R = Rz(yaw) Ry(pitch) Rx(roll),
positive pitch looks down), so the optimiser searches over body roll/pitch/yaw and converts here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

#: Columns: the optical frame's axes expressed in the body frame (x_opt = -y, y_opt = -z, z_opt = x).
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)]])


def _quat_from_matrix(m: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix, from its largest component (Shepperd's method: stable
    for every rotation), sign fixed to w >= 0 as scipy's."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    k = int(np.argmax([m[0, 0], m[1, 1], m[2, 2], tr]))
    if k == 3:
        w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
        f = 0.25 / w
        q = [(m[2, 1] - m[1, 2]) * f, (m[0, 2] - m[2, 0]) * f, (m[1, 0] - m[0, 1]) * f, w]
    else:
        i, j, l = k, (k + 1) % 3, (k + 2) % 3
        a = 0.5 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[l, l], 0.0))
        f = 0.25 / a
        q = [0.0, 0.0, 0.0, (m[l, j] - m[j, l]) * f]
        q[i], q[j], q[l] = a, (m[j, i] + m[i, j]) * f, (m[l, i] + m[i, l]) * f
    out = np.array(q)
    return out if out[3] >= 0 else -out


def _matrix_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


# The conversions above are closed forms instead of scipy's Rotation: the search builds a pose per
# loss evaluation, and scipy's general conversions (with their checks) cost ~10 % of a calibration.


@dataclass(frozen=True)
class Pose:
    """Optical frame of a camera in the map frame."""

    translation: np.ndarray  # (3,) camera centre in the map frame, metres
    quaternion: np.ndarray  # (4,) x, y, z, w of the optical frame in the map frame

    def __post_init__(self) -> None:
        t = np.asarray(self.translation, dtype=float).reshape(3)
        q = np.asarray(self.quaternion, dtype=float).reshape(4)
        if not np.all(np.isfinite(t)) or not np.all(np.isfinite(q)):
            raise ValueError("pose contains NaN or infinite values")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"rotation is not a unit quaternion (norm {norm:.6g})")
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "quaternion", q / norm)

    @classmethod
    def from_matrix(cls, rotation: np.ndarray, translation: np.ndarray) -> "Pose":
        """From the optical frame's rotation matrix in the map frame."""
        return cls(np.asarray(translation, float), _quat_from_matrix(np.asarray(rotation, float)))

    @classmethod
    def from_body_rpy(cls, translation: np.ndarray, rpy_rad: np.ndarray) -> "Pose":
        """From body-frame roll, pitch, yaw in radians."""
        r_body = _matrix_from_rpy(float(rpy_rad[0]), float(rpy_rad[1]), float(rpy_rad[2]))
        return cls.from_matrix(r_body @ BODY_FROM_OPTICAL, translation)

    @classmethod
    def from_body_rpy_deg(cls, translation: np.ndarray, rpy_deg: np.ndarray) -> "Pose":
        return cls.from_body_rpy(translation, np.radians(np.asarray(rpy_deg, float)))

    @cached_property
    def rotation(self) -> np.ndarray:
        """3x3 rotation of the optical frame in the map (columns: optical axes in map)."""
        return _matrix_from_quat(self.quaternion)

    def body_rpy(self) -> np.ndarray:
        """Body-frame roll, pitch, yaw in radians (at pitch +-90 deg, where roll and yaw are one
        axis, roll is 0)."""
        m = self.rotation @ BODY_FROM_OPTICAL.T
        pitch = math.asin(min(1.0, max(-1.0, -m[2, 0])))
        if abs(m[2, 0]) > 1.0 - 1e-12:
            return np.array([0.0, pitch, math.atan2(-m[0, 1], m[1, 1])])
        return np.array([math.atan2(m[2, 1], m[2, 2]), pitch, math.atan2(m[1, 0], m[0, 0])])

    def body_rpy_deg(self) -> np.ndarray:
        return np.degrees(self.body_rpy())

    def vector(self) -> np.ndarray:
        """x, y, z, roll, pitch, yaw (radians): the optimiser's parameters."""
        return np.concatenate([self.translation, self.body_rpy()])

    @classmethod
    def from_vector(cls, v: np.ndarray) -> "Pose":
        return cls.from_body_rpy(v[:3], v[3:6])

    def world_to_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) with X_cam = R @ X_map + t."""
        r = self.rotation.T
        return r, -r @ self.translation

    def transform_points(self, points: np.ndarray) -> np.ndarray:
        """Map-frame points into the optical frame."""
        r, t = self.world_to_camera()
        return points @ r.T + t


def translation_error(a: Pose, b: Pose) -> float:
    """Distance between camera centres, metres."""
    return float(np.linalg.norm(a.translation - b.translation))


def rotation_error_deg(a: Pose, b: Pose) -> float:
    """Geodesic angle between two orientations, degrees."""
    rel = Rotation.from_quat(a.quaternion).inv() * Rotation.from_quat(b.quaternion)
    return float(np.degrees(rel.magnitude()))


def perturbed_initial(truth: Pose, rng: np.random.Generator, metres: float = 1.0,
                      degrees: float = 2.0) -> Pose:
    """A demo starting guess: up to ``metres`` per axis and ``degrees`` in pitch and yaw off."""
    rpy = truth.body_rpy_deg()
    d_rpy = np.array([0.0, *rng.uniform(-degrees, degrees, 2)])
    return Pose.from_body_rpy_deg(truth.translation + rng.uniform(-metres, metres, 3), rpy + d_rpy)
