"""A small synthetic street for map-building tests: surfaces sampled as points, scans cut from it.

Not a lidar simulation (no occlusion, uniform density): enough geometry (ground, facades in
two orientations, poles) to pin all six degrees of freedom of ICP, with known true poses.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import KITTI_ID

ROAD, BUILDING, POLE, CAR = (KITTI_ID[n] for n in ("road", "building", "pole", "car"))
LIDAR_HEIGHT = 1.8


def _box_surface(rng, lo, hi, spacing):
    """Points on the four walls and the roof of an axis-aligned box."""
    pts = []
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    for fixed, axis in ((y0, 1), (y1, 1), (x0, 0), (x1, 0)):
        u_lo, u_hi = (x0, x1) if axis == 1 else (y0, y1)
        n = int((u_hi - u_lo) * (z1 - z0) / spacing**2)
        u, z = rng.uniform(u_lo, u_hi, n), rng.uniform(z0, z1, n)
        wall = np.c_[u, np.full(n, fixed), z] if axis == 1 else np.c_[np.full(n, fixed), u, z]
        pts.append(wall)
    n = int((x1 - x0) * (y1 - y0) / spacing**2)
    pts.append(np.c_[rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), np.full(n, z1)])
    return np.concatenate(pts)


def make_world(length: float = 30.0, seed: int = 0, cars: int = 4) -> LabelledCloud:
    """Ground, buildings on both sides (turned a little, so no direction is featureless), poles
    and parked/driving cars along x in [-35, length + 35]."""
    rng = np.random.default_rng(seed)
    x0, x1 = -35.0, length + 35.0
    parts, labels = [], []
    n = int((x1 - x0) * 70 / 0.3**2)
    ground = np.c_[rng.uniform(x0, x1, n), rng.uniform(-35, 35, n), np.zeros(n)]
    parts.append(ground)
    labels.append(np.full(n, ROAD))
    for side in (-1, 1):
        x = x0
        while x < x1:
            w, d, h = rng.uniform(5, 12), rng.uniform(5, 10), rng.uniform(4, 14)
            y = side * rng.uniform(9, 13)
            box = _box_surface(rng, (x, min(y, y + side * d), 0), (x + w, max(y, y + side * d), h),
                               0.2)
            yaw = np.radians(rng.uniform(-8, 8))  # not all facades parallel to the street
            c = np.array([x + w / 2, y, 0])
            box = (box - c) @ Rotation.from_euler("z", yaw).as_matrix().T + c
            parts.append(box)
            labels.append(np.full(len(box), BUILDING))
            x += w + rng.uniform(2, 6)
    for px in np.arange(x0 + 3, x1, 9.0):
        for side in (-1, 1):
            k = 300
            a, z = rng.uniform(0, 2 * np.pi, k), rng.uniform(0, 6, k)
            pole = np.c_[px + 0.15 * np.cos(a), side * 6.5 + 0.15 * np.sin(a), z]
            parts.append(pole)
            labels.append(np.full(k, POLE))
    for i in range(cars):
        cx = x0 + 10 + i * (x1 - x0 - 20) / max(cars, 1)
        cy = 4.5 if i % 2 else 0.0  # every other car on the vehicle's own lane
        car = _box_surface(rng, (cx, cy - 0.9, 0.2), (cx + 4.2, cy + 0.9, 1.5), 0.1)
        parts.append(car)
        labels.append(np.full(len(car), CAR))
    return LabelledCloud(np.concatenate(parts), np.concatenate(labels).astype(np.uint16))


def drive(n: int, step: float = 1.0, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) lidar poses along x with a gentle weave in y and yaw."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    phase = rng.uniform(0, 2 * np.pi)
    for i in range(n):
        x = i * step
        poses[i, :3, 3] = [x, 0.4 * np.sin(0.15 * x + phase), LIDAR_HEIGHT]
        yaw = 0.06 * np.cos(0.15 * x + phase)
        poses[i, :3, :3] = Rotation.from_euler("zyx", [yaw, 0.004 * np.sin(x), 0.0]).as_matrix()
    return poses


def scan_from(world: LabelledCloud, pose: np.ndarray, seed: int, radius: float = 35.0,
              keep: float = 0.6, noise: float = 0.01) -> LabelledCloud:
    """A lidar-frame scan: the world points within ``radius``, a random ``keep`` fraction of
    them (different per scan), with ``noise`` metres of Gaussian jitter."""
    rng = np.random.default_rng(seed)
    d = world.xyz - pose[:3, 3]
    mask = (np.einsum("ij,ij->i", d, d) < radius**2) & (rng.random(len(d)) < keep)
    xyz = (d[mask] @ pose[:3, :3]) + rng.normal(0, noise, (int(mask.sum()), 3))
    return LabelledCloud(xyz, world.label[mask], {"intensity": rng.random(int(mask.sum()))})
