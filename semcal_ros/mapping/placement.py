"""The scans of a vehicle frame placed in the anchor scan's lidar frame (de-skewed, registered).

A camera on a vehicle at frame i is tied to scan i (same rig, same instant), so the map of its
calibration case must be expressed in scan i's lidar frame with scan i exactly where the sensor
measured it; the other scans are placed around it. :func:`place_scans` does that: relative poses
from the given ones, de-skew with the motion between consecutive poses (``deskew.py``), then
multiway ICP with the anchor held fixed (``registration.register_chain``), then de-skew again
with the refined motion (ICP's relative poses are closer to the true motion than a drifting
odometry, and the velocity the de-skew uses comes from them) and a final registration.

Unlike :func:`semcal_ros.mapping.build_map`, nothing is re-anchored to the mean of the poses: the
anchor's transform is the identity by construction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.mapping.deskew import (
    DeskewParams, azimuth_times, correct_vertical_angle, deskew_points, twists_from_poses)
from semcal_ros.mapping.filters import apply_rigid
from semcal_ros.mapping.registration import (
    PairResult, RegistrationParams, register_chain, registration_cloud, rotation_deg)


@dataclass
class PlacementParams:
    """What :func:`place_scans` does beyond the call's switches."""

    deskew: DeskewParams = field(default_factory=DeskewParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    rounds: int = 4  # at most this many de-skew + ICP rounds: each de-skews with the motion
    # the previous one refined (noisy poses give a noisy velocity, which skews the scans)
    converged_m: float = 0.005  # stop once a round moves no scan by more than this (m)
    loop_span: int = 2  # ICP edges between scans up to this many apart (neighbours: 1)
    d_max: float = 60.0  # m, points farther from their sensor are left out of ICP (not of xyz)
    vertical_angle_deg: float = 0.0  # elevation correction before everything (KITTI HDL-64E:
    # 0.205, see deskew.correct_vertical_angle); 0 for a correctly calibrated sensor

    def __post_init__(self) -> None:
        if self.rounds < 1 or self.loop_span < 1 or not self.d_max > 0:
            raise ValueError("placement needs rounds >= 1, loop_span >= 1 and d_max > 0")


@dataclass
class Placement:
    """Where :func:`place_scans` put each scan, and its points after de-skew."""

    transforms: list[np.ndarray]  # per scan 4x4: its (de-skewed) lidar frame -> the anchor's
    xyz: list[np.ndarray]  # per scan (N, 3): de-skewed points in the scan's own lidar frame
    anchor: int
    pairs: list[PairResult] = field(default_factory=list)  # ICP edges of the last round
    deskewed: bool = False

    def in_anchor_frame(self, i: int) -> np.ndarray:
        """Scan i's de-skewed points in the anchor scan's lidar frame."""
        return apply_rigid(self.xyz[i], self.transforms[i])


def place_scans(scans: list[np.ndarray], poses: list[np.ndarray], anchor: int,
                times: list[np.ndarray | None] | None = None, refine: bool = True,
                deskew: bool = True, params: PlacementParams | None = None,
                stamps: list[float] | np.ndarray | None = None) -> Placement:
    """Each scan's transform into the ANCHOR scan's lidar frame (the anchor's is the identity).

    ``scans``: (N, 3) xyz per scan in its lidar frame, in time order; ``poses``: 4x4 lidar -> map
    per scan (any map frame: only relative poses are used); ``times``: per scan, seconds of each
    point from the instant its pose refers to (None: from the azimuth, per ``params.deskew``);
    ``stamps``: the poses' times (default: one ``deskew.period`` apart). Raises ValueError (one
    line) on inconsistent input.
    """
    params = params or PlacementParams()
    n = len(scans)
    if n == 0 or len(poses) != n:
        raise ValueError(f"place_scans needs one pose per scan, got {n} scans and "
                         f"{len(poses)} poses")
    if not 0 <= anchor < n:
        raise ValueError(f"anchor {anchor} is not a scan index (0-{n - 1})")
    if times is not None and len(times) != n:
        raise ValueError(f"{len(times)} time arrays for {n} scans")
    raw = []
    for i, xyz in enumerate(scans):
        xyz = np.asarray(xyz, float)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"scan {i}: points must be (N, 3), got {xyz.shape}")
        raw.append(correct_vertical_angle(xyz, params.vertical_angle_deg))
    poses_arr = np.asarray(poses, float)
    if poses_arr.shape != (n, 4, 4) or not np.all(np.isfinite(poses_arr)):
        raise ValueError(f"poses must be {n} finite 4x4 matrices, got shape {poses_arr.shape}")
    stamps_arr = (np.arange(n) * params.deskew.period if stamps is None
                  else np.asarray(stamps, float).reshape(-1))
    if len(stamps_arr) != n or np.any(np.diff(stamps_arr) <= 0):
        raise ValueError("stamps must be one per scan and strictly increasing")
    relative = np.linalg.inv(poses_arr[anchor]) @ poses_arr  # lidar i -> anchor lidar

    point_times: list[np.ndarray | None] = [None] * n
    use_deskew = deskew and params.deskew.enabled and params.deskew.source != "none"
    if use_deskew:
        for i in range(n):
            given = None if times is None else times[i]
            if given is not None:
                given = np.asarray(given, float).reshape(-1)
                if len(given) != len(raw[i]):
                    raise ValueError(f"scan {i}: {len(given)} point times for {len(raw[i])} "
                                     "points")
                point_times[i] = given
            elif params.deskew.source in ("auto", "azimuth"):
                point_times[i] = azimuth_times(raw[i], params.deskew)

    xyz = [r.copy() for r in raw]
    pairs: list[PairResult] = []
    rounds = params.rounds if refine else 1
    for _ in range(rounds):
        if use_deskew:
            twists = twists_from_poses(relative, stamps_arr, params.deskew.max_gap)
            xyz = [deskew_points(raw[i], point_times[i], twists[i])
                   if point_times[i] is not None else raw[i] for i in range(n)]
        if not refine:
            break
        clouds = []
        for i in range(n):
            near = np.einsum("ij,ij->i", xyz[i], xyz[i]) <= params.d_max ** 2
            clouds.append(registration_cloud(apply_rigid(xyz[i][near], relative[i]),
                                             relative[i][:3, 3], params.registration))
        result = register_chain(clouds, anchor, params.registration, params.loop_span)
        relative = np.array([c @ r for c, r in zip(result.corrections, relative)])
        pairs = result.pairs
        moved = max(float(np.linalg.norm(c[:3, 3])) + np.radians(rotation_deg(c)) * params.d_max
                    / 2 for c in result.corrections)
        if not use_deskew or moved < params.converged_m:
            break  # without de-skew a second round starts where the first ended
    if use_deskew and refine:  # the points with the motion of the final placement
        twists = twists_from_poses(relative, stamps_arr, params.deskew.max_gap)
        xyz = [deskew_points(raw[i], point_times[i], twists[i])
               if point_times[i] is not None else raw[i] for i in range(n)]
    relative[anchor] = np.eye(4)
    return Placement(list(relative), xyz, anchor, pairs, use_deskew)


@dataclass
class PlacedMap:
    """A vehicle frame's map and the scans it was built from, as placed: ``scans[i]`` de-skewed in
    its own lidar frame (time fields dropped, other fields kept), ``poses[i]`` its refined
    lidar -> map transform. Building a map again from
    these scans and poses (no ICP, no de-skew) gives ``map`` (what a scene's ``scans/`` holds)."""

    map: LabelledCloud
    scans: list[LabelledCloud]
    poses: list[np.ndarray]


def placed_map(clouds: list[LabelledCloud], poses: list[np.ndarray], stamps: list[float],
               d_max: float, voxel: float, anchor: int | None = None,
               params: PlacementParams | None = None) -> PlacedMap:
    """The labelled map of a vehicle frame's scans, in the poses' map frame: placed by
    :func:`place_scans` around the anchor scan (held at its given pose; default: the scan whose
    pose is closest to the identity, i.e. the scan whose lidar frame is the map frame), with
    per-point times from a ``t``/``time``/``timestamp`` field, else the azimuth; limited to
    ``d_max``, voxel-downsampled with the majority label per voxel; dynamic classes are left to
    the caller."""
    from semcal_ros.mapping import MapBuildParams, ScanInput, build_map
    from semcal_ros.mapping.deskew import TIME_FIELDS, point_times

    params = params or PlacementParams()
    poses_arr = np.asarray(poses, float)
    if anchor is None:
        anchor = int(np.argmin([np.abs(p - np.eye(4)).sum() for p in poses_arr]))
    times = [point_times(c.xyz, c.extra, params.deskew) for c in clouds]
    placed = place_scans([c.xyz for c in clouds], list(poses_arr), anchor, times=times,
                         params=params, stamps=stamps if len(clouds) > 1 else None)
    # de-skewed: their time fields go (a builder would de-skew them again), the rest stays
    scans = [LabelledCloud(xyz, c.label, {k: v for k, v in c.extra.items() if k not in TIME_FIELDS})
             for c, xyz in zip(clouds, placed.xyz)]
    in_map = [poses_arr[anchor] @ t for t in placed.transforms]
    inputs = [ScanInput(c, pose, s, f"{i:06d}")
              for i, (c, pose, s) in enumerate(zip(scans, in_map, stamps))]
    result = build_map(inputs, MapBuildParams(d_max=d_max, voxel=voxel, icp=False,
                                              remove_dynamic=False))
    if result.skipped:
        raise ValueError(f"scans skipped by the map builder: {result.skipped}")
    return PlacedMap(result.map, scans, in_map)


__all__ = ["PlacedMap", "Placement", "PlacementParams", "place_scans", "placed_map"]
