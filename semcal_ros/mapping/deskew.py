"""Motion compensation (de-skew) of lidar sweeps.

A spinning lidar takes a sweep over one revolution (KITTI's HDL-64E: 0.1 s) while the vehicle
drives on (KITTI 00 frame 0: 0.86 m per sweep). Each point is measured in the lidar frame *of its
own instant*; treating the sweep as a rigid snapshot puts points measured before or after the
moment the scan's pose refers to up to half a sweep's motion out of place (KITTI: up to 0.43 m
behind the car, where the sweep starts and ends). De-skew moves every point into the lidar frame
of the reference instant with the motion between consecutive poses, interpolated on SE(3) at
constant body velocity: ``x_ref = exp(t * xi) @ x`` for a point at time ``t`` (seconds from the
reference instant) and the body twist ``xi`` (per second) of the sensor.

Per-point time comes from a point field (``t``, ``time`` or ``timestamp``, as the Ouster,
Velodyne and Livox ROS drivers publish) or, for a spinning lidar without one, from the azimuth.
KITTI's convention, found from the data (:func:`seam_offset`, docs/mapping.md): the pose is
taken (and the camera triggered) when the lidar faces forward, a sweep starts and ends behind the
car, and in the scan's x/y the points' time order runs counterclockwise seen from above: raw
scans are torn 0.84-0.88 m apart along x at the rear seam, de-skewed counterclockwise with
poses.txt's motion the tear is -0.03..0.08 m, clockwise it doubles to 1.7 m. A point at azimuth
``a`` (atan2(y, x)) is then taken at ``t = a / (2 pi) * period``, ``a`` wrapped to (-pi, pi].

No ROS here; :mod:`semcal_ros.mapping.placement` and the map builder call it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy.spatial.transform import Rotation

#: Point fields that carry per-point time, in the order they are looked for.
TIME_FIELDS = ("t", "time", "timestamp")


@dataclass
class DeskewParams:
    """How scans are motion-compensated (``mapping.deskew.*`` in config/map_builder.yaml)."""

    enabled: bool = True  # False: scans are rigid snapshots (the old behaviour)
    source: str = "auto"  # auto: time field if present, else azimuth; field | azimuth | none
    period: float = 0.1  # s per revolution (KITTI, Velodyne at 10 Hz); also the scan spacing
    # when no stamps are given
    direction: str = "counterclockwise"  # the spin seen from above (z up), in the time order
    # of the points: KITTI's scans close their rear seam counterclockwise (docs/mapping.md)
    reference_azimuth_deg: float = 0.0  # where the lidar faces at the scan's pose instant
    # (KITTI: forward, the camera trigger); the sweep is cut opposite it
    time_unit: float = 0.0  # seconds per unit of the time field; 0: guessed from its span
    # (ns, us or s)
    pose_at: float = 0.0  # where in the time field's span the scan's pose instant lies:
    # 0 first point (Ouster, Velodyne drivers), 0.5 middle, 1 last point
    max_gap: float = 0.5  # s: consecutive poses farther apart give no velocity (no de-skew)

    def __post_init__(self) -> None:
        if self.source not in ("auto", "field", "azimuth", "none"):
            raise ValueError(f"deskew.source must be auto, field, azimuth or none, "
                             f"got '{self.source}'")
        if self.direction not in ("clockwise", "counterclockwise"):
            raise ValueError(f"deskew.direction must be clockwise or counterclockwise, "
                             f"got '{self.direction}'")
        if not self.period > 0 or self.time_unit < 0 or not 0 <= self.pose_at <= 1 \
                or not self.max_gap > 0:
            raise ValueError("deskew needs period > 0, time_unit >= 0, 0 <= pose_at <= 1 and "
                             "max_gap > 0")


# --- SE(3) ---------------------------------------------------------------------------------

def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def se3_log(matrix: np.ndarray) -> np.ndarray:
    """Twist (rho, phi) of a 4x4 rigid transform: ``se3_exp(se3_log(T)) == T``."""
    m = np.asarray(matrix, float)
    phi = Rotation.from_matrix(m[:3, :3]).as_rotvec()
    theta = float(np.linalg.norm(phi))
    k = _hat(phi)
    if theta < 1e-6:
        v_inv = np.eye(3) - 0.5 * k + k @ k / 12.0
    else:
        v_inv = (np.eye(3) - 0.5 * k
                 + (1.0 / theta**2 - (1 + np.cos(theta)) / (2 * theta * np.sin(theta))) * k @ k)
    return np.concatenate([v_inv @ m[:3, 3], phi])


def se3_exp_points(twist: np.ndarray, times: np.ndarray) -> tuple[Rotation, np.ndarray]:
    """Rotations and translations of ``exp(t * twist)`` for every time ``t`` (vectorised).

    ``exp(xi) = [R, V rho]`` with ``V rho = rho + a (phi x rho) + b (phi x (phi x rho))``,
    ``a = (1 - cos th) / th^2``, ``b = (th - sin th) / th^3``; series below 1e-4 rad.
    """
    rho, phi = np.asarray(twist[:3], float), np.asarray(twist[3:], float)
    t = np.asarray(times, float).reshape(-1)
    theta = np.abs(t) * np.linalg.norm(phi)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    c1, c2 = np.cross(phi, rho), np.cross(phi, np.cross(phi, rho))
    trans = (t[:, None] * rho + (a * t**2)[:, None] * c1 + (b * t**3)[:, None] * c2)
    return Rotation.from_rotvec(t[:, None] * phi), trans


# --- velocity from poses -------------------------------------------------------------------

def body_twist(pose_a: np.ndarray, pose_b: np.ndarray, dt: float) -> np.ndarray:
    """Constant body velocity (twist per second) that moves ``pose_a`` to ``pose_b`` in ``dt``."""
    if not dt > 0:
        raise ValueError(f"poses for a velocity must be in time order, got dt = {dt} s")
    return se3_log(np.linalg.inv(pose_a) @ pose_b) / dt


def twists_from_poses(poses: np.ndarray, stamps: np.ndarray, max_gap: float = 0.5
                      ) -> list[np.ndarray | None]:
    """Per pose, the sensor's body twist: the mean of the motions to its neighbours (central
    difference; one-sided at the ends). None where no neighbour lies within ``max_gap`` s."""
    poses = np.asarray(poses, float)
    stamps = np.asarray(stamps, float)
    n = len(poses)
    out: list[np.ndarray | None] = []
    for i in range(n):
        parts = []
        if i > 0 and 0 < stamps[i] - stamps[i - 1] <= max_gap:
            parts.append(body_twist(poses[i - 1], poses[i], stamps[i] - stamps[i - 1]))
        if i + 1 < n and 0 < stamps[i + 1] - stamps[i] <= max_gap:
            parts.append(body_twist(poses[i], poses[i + 1], stamps[i + 1] - stamps[i]))
        out.append(np.mean(parts, axis=0) if parts else None)
    return out


# --- per-point time ------------------------------------------------------------------------

def azimuth_times(xyz: np.ndarray, params: DeskewParams = DeskewParams()) -> np.ndarray:
    """Seconds from the pose instant of each point of a spinning lidar's sweep, from its azimuth
    (see the module docstring); the sweep is cut opposite ``reference_azimuth_deg``."""
    xyz = np.asarray(xyz, float)
    az = np.arctan2(xyz[:, 1], xyz[:, 0]) - np.radians(params.reference_azimuth_deg)
    az = np.angle(np.exp(1j * az))  # wrapped to (-pi, pi]
    sign = -1.0 if params.direction == "clockwise" else 1.0
    return sign * az / (2 * np.pi) * params.period


def field_times(values: np.ndarray, params: DeskewParams = DeskewParams()) -> np.ndarray:
    """Seconds from the pose instant from a driver's per-point time field.

    Drivers differ in unit (Ouster ``t``: ns; Velodyne ``time``: s; Livox ``timestamp``: ns,
    absolute) and in origin, so only differences are used: ``time_unit`` (or a guess from the
    span: one sweep lasts well under a second) and ``pose_at`` place them.
    """
    v = np.asarray(values, np.float64).reshape(-1)
    if len(v) == 0:
        return v
    finite = np.isfinite(v)
    if not finite.any():
        raise ValueError("per-point time field holds no finite value")
    lo, hi = float(v[finite].min()), float(v[finite].max())
    unit = params.time_unit
    if unit == 0:
        span = hi - lo
        unit = 1e-9 if span > 1e4 else 1e-6 if span > 10 else 1.0
    rel = (np.where(finite, v, lo) - lo) * unit
    return rel - params.pose_at * (hi - lo) * unit


def point_times(xyz: np.ndarray, fields: Mapping[str, np.ndarray] | None,
                params: DeskewParams = DeskewParams()) -> np.ndarray | None:
    """Per-point seconds from the pose instant, from the source ``params`` choose; None when
    there is none (source ``none``, or ``field`` without a time field)."""
    if not params.enabled or params.source == "none":
        return None
    if params.source in ("auto", "field") and fields:
        for name in TIME_FIELDS:
            if name in fields:
                return field_times(fields[name], params)
    if params.source == "field":
        return None
    return azimuth_times(xyz, params)


# --- the correction --------------------------------------------------------------------------

def deskew_points(xyz: np.ndarray, times: np.ndarray, twist: np.ndarray | None) -> np.ndarray:
    """Points moved into the lidar frame of the pose instant: ``exp(t * twist) @ x``."""
    xyz = np.asarray(xyz, float)
    if twist is None or len(xyz) == 0:
        return xyz.copy()
    times = np.asarray(times, float).reshape(-1)
    if len(times) != len(xyz):
        raise ValueError(f"{len(times)} point times for {len(xyz)} points")
    rot, trans = se3_exp_points(twist, times)
    return rot.apply(xyz) + trans


def correct_vertical_angle(xyz: np.ndarray, offset_deg: float) -> np.ndarray:
    """Each point's elevation raised by ``offset_deg`` (rotation about the axis ``p x z``), range
    and azimuth kept: the KITTI HDL-64E's known intrinsic error (about 0.2 deg; IMLS-SLAM,
    CT-ICP and kiss-icp's KITTI loader apply 0.205 deg), which bends the ground into a bowl."""
    xyz = np.asarray(xyz, float)
    if offset_deg == 0 or len(xyz) == 0:
        return xyz.copy()
    axis = np.cross(xyz, np.array([0.0, 0.0, 1.0]))
    norm = np.linalg.norm(axis, axis=1)
    ok = norm > 1e-9
    axis[ok] /= norm[ok, None]
    axis[~ok] = 0.0
    return Rotation.from_rotvec(np.radians(offset_deg) * axis).apply(xyz)


__all__ = ["DeskewParams", "TIME_FIELDS", "azimuth_times", "body_twist", "correct_vertical_angle",
           "seam_offset",
           "deskew_points", "field_times", "point_times", "se3_exp_points", "se3_log",
           "twists_from_poses"]


def seam_offset(xyz: np.ndarray, params: DeskewParams = DeskewParams(), width_deg: float = 4.0,
                ranges: tuple[float, float] = (4.0, 30.0), step: float = 0.01,
                search: float = 2.0) -> float:
    """Where a sweep's two ends disagree: the shift along x (metres, lidar frame: the vehicle's
    forward axis) that best lays the points just after the seam onto those just before it.

    A sweep cut opposite ``reference_azimuth_deg`` joins its first and last moments there: if the
    sensor moved during the sweep and the points were not de-skewed, the two sides of the seam
    are torn apart by the motion of one sweep; after a correct de-skew the tear is gone. This is
    how the spin direction and cut of a dataset are read off the data (docs/mapping.md). Shift
    searched on a grid of ``step`` in +-``search`` m (then finer around the best), scored by the
    median distance to the nearest point of the other side. Sideways the two sides do not
    overlap (left and right of the seam), so only x is searched.
    """
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, float)
    cut = np.radians(params.reference_azimuth_deg + 180.0)
    az = np.angle(np.exp(1j * (np.arctan2(xyz[:, 1], xyz[:, 0]) - cut)))  # 0 at the seam
    rng = np.hypot(xyz[:, 0], xyz[:, 1])
    near = (rng > ranges[0]) & (rng < ranges[1]) & (np.abs(az) < np.radians(width_deg))
    before, after = xyz[near & (az > 0)], xyz[near & (az <= 0)]
    if len(before) < 50 or len(after) < 50:
        raise ValueError("too few points at the sweep's seam to measure it")
    tree = cKDTree(before)
    best = 0.0
    for coarse in (5 * step, step):
        candidates = best + np.arange(-search, search + coarse / 2, coarse)
        scores = [np.median(tree.query(after + [c, 0.0, 0.0], workers=1)[0]) for c in candidates]
        best = float(candidates[int(np.argmin(scores))])
        search = 10 * coarse
    return best
