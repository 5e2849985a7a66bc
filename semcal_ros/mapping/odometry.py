"""Where each scan of a short recording was taken, from the scans alone (no poses file).

A vehicle camera's frame comes with the lidar scan taken at that moment and, in most recordings,
its neighbours; the neighbours fill the single scan's gaps (issue 41: one scan of a narrow
lidar covers a band at street level). Without the recording's poses, each scan is registered to
the one before it with generalized ICP (``small_gicp`` through :func:`registration.pairwise_icp`,
coarse to fine), started from the motion of the previous pair (constant velocity: a car moves
0.7-0.9 m per KITTI sweep, about a correspondence distance, and the first pair starts from no
motion). The chain is only the start: :func:`semcal_ros.mapping.placement.place_scans` then
de-skews the scans with it and refines every pose by multiway ICP with the camera's scan held
fixed, as for given poses. KISS-ICP does the same job for long drives; here a handful of scans
is registered with the ICP the map builder already uses, so one registration serves both.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from semcal_ros.mapping.registration import (RegistrationParams, pairwise_icp,
                                             registration_cloud)


def scan_odometry(scans: list[np.ndarray], params: RegistrationParams | None = None
                  ) -> list[np.ndarray]:
    """4x4 pose of each scan's lidar frame in the first scan's lidar frame (the first is the
    identity), from scan-to-scan ICP in time order. Raises ValueError (one line) when a scan
    cannot be registered to the one before it."""
    # the whole motion between two sweeps is the ICP's result here, not a small correction
    params = replace(params or RegistrationParams(), max_correction_m=5.0,
                     max_correction_deg=15.0)
    poses = [np.eye(4)]
    if len(scans) < 2:
        return poses
    clouds = [registration_cloud(np.asarray(xyz, np.float64), None, params) for xyz in scans]
    step = np.eye(4)  # scan i -> scan i-1 of the previous pair: the next pair's start
    for i in range(1, len(scans)):
        pair = pairwise_icp(clouds[i], clouds[i - 1], params, i, i - 1, init=step)
        if not pair.accepted:
            raise ValueError(f"scan {i + 1} could not be registered to scan {i} "
                             f"({pair.reason}): give their poses (--poses)")
        step = pair.transformation
        poses.append(poses[-1] @ step)
    return poses


__all__ = ["scan_odometry"]
