"""Measuring maps and poses: pose noise for experiments, pose errors, scan-to-scan alignment.

Lidar-only registration cannot see where the whole map sits (a rigid motion of everything leaves
every scan-to-scan residual unchanged), so pose errors are reported both as they are and after
removing that one common transform (:func:`remove_common_transform`), the part registration is
responsible for.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from semcal_ros.mapping.registration import anchor, rotation_deg


def displace_poses(poses: np.ndarray, translation_m: float, rotation_deg_: float,
                   seed: int | None = 0) -> np.ndarray:
    """Each pose moved by exactly ``translation_m`` and turned by exactly ``rotation_deg_``
    (a fixed-size error per scan; the scenes' smooth 1-sigma localisation error is
    :func:`semcal_tools.scenes.generate.localisation_noise`).

    Directions and axes are uniformly random (seeded). The noise acts in the sensor's own frame
    (``pose @ noise``): a heading error turns the scan about the lidar, as a bad compass would.
    """
    poses = np.asarray(poses, float)
    rng = np.random.default_rng(seed)
    out = poses.copy()
    for i in range(len(poses)):
        direction = rng.normal(size=3)
        axis = rng.normal(size=3)
        noise = np.eye(4)
        noise[:3, 3] = translation_m * direction / np.linalg.norm(direction)
        noise[:3, :3] = Rotation.from_rotvec(
            np.radians(rotation_deg_) * axis / np.linalg.norm(axis)).as_matrix()
        out[i] = poses[i] @ noise
    return out


def pose_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: position error (metres) and rotation error (degrees)."""
    shift = np.linalg.norm(estimated[:, :3, 3] - truth[:, :3, 3], axis=1)
    angle = np.array([rotation_deg(np.linalg.inv(t) @ e) for e, t in zip(estimated, truth)])
    return shift, angle


def remove_common_transform(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``estimated`` moved by the one rigid transform that best matches it to ``truth``.

    The transform is the mean (about the trajectory's centroid) of the per-pose discrepancies,
    the same averaging the registration uses to anchor its groups.
    """
    discrepancy = [e @ np.linalg.inv(t) for e, t in zip(estimated, truth)]
    center = truth[:, :3, 3].mean(axis=0)
    fixed = anchor(discrepancy, np.ones(len(truth)), center)
    return np.array([d @ t for d, t in zip(fixed, truth)])


def above_ground(points_lidar: np.ndarray, clearance: float = 0.3, search_radius: float = 30.0,
                 seed: int = 0) -> np.ndarray:
    """Mask of points more than ``clearance`` above the ground plane (lidar frame).

    The ground is the dominant plane (RANSAC) among points below the sensor within
    ``search_radius``; ground points make scan-to-scan distances look better than they are,
    because a plane slid along itself still matches.
    """
    xyz = np.asarray(points_lidar, float)
    near = (np.hypot(xyz[:, 0], xyz[:, 1]) < search_radius) & (xyz[:, 2] < 0)
    if near.sum() < 100:
        raise ValueError("too few points below the sensor to find the ground")
    import open3d as o3d  # here: half a second of start-up for processes that never need it

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz[near]))
    o3d.utility.random.seed(seed)
    plane, _ = pcd.segment_plane(distance_threshold=0.15, ransac_n=3, num_iterations=300)
    normal, d = np.asarray(plane[:3]), float(plane[3])
    if d < 0:  # orient the normal so that the sensor (origin) is on the positive side
        normal, d = -normal, -d
    height = xyz[:, 0] * normal[0] + xyz[:, 1] * normal[1] + xyz[:, 2] * normal[2] + d
    return height > clearance  # (no BLAS product: see filters.apply_rigid)


def scan_alignment(scans_map: list[np.ndarray], workers: int = 1) -> float:
    """Median distance from each scan's points to the nearest point of any other scan.

    Scans are given in the map frame (usually their above-ground points). The better the poses,
    the closer surfaces seen by several scans coincide; with perfect poses what remains is the
    sampling gap of the lidar.
    """
    if len(scans_map) < 2:
        raise ValueError("alignment needs at least two scans")
    distances = []
    for i, pts in enumerate(scans_map):
        others = np.concatenate([s for j, s in enumerate(scans_map) if j != i])
        d, _ = cKDTree(others).query(pts, workers=workers)
        distances.append(d)
    return float(np.median(np.concatenate(distances)))
