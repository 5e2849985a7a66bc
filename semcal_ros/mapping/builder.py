"""Scans and poses into one labelled map: the paper's recursive grouped multiway ICP.

One engine serves both doors. :class:`StreamingMapBuilder` takes time-ordered scans one at a time
(the live node); :func:`build_map` feeds it a list (the command line). Scans enter level 0 of a
stack; whenever a level holds three clouds, they are registered together (multiway ICP), merged,
voxel-downsampled and pushed one level up, like carries in a base-3 counter. Work is therefore
done as groups fill, every level stays voxel-downsampled, and at most two clouds wait on each of
the log3(N) levels, so memory follows the mapped area, not the number of scans. ``finish``
registers whatever is left, lowest level first, until one cloud remains.

Poses are of the lidar in the map frame (or of the vehicle, with ``lidar_extrinsic`` the lidar in
the vehicle frame). Per scan the builder keeps only its prior pose and its accumulated correction,
so the refined pose of scan s is ``correction[s] @ prior[s]``.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.mapping import filters
from semcal_ros.mapping import kernels
from semcal_ros.mapping.deskew import (
    TIME_FIELDS, DeskewParams, body_twist, correct_vertical_angle, point_times,
    twists_from_poses)
from semcal_ros.mapping.pose_stream import PoseStream, as_matrix
from semcal_ros.mapping.registration import (
    PairResult, RegistrationCloud, RegistrationParams, merge_registration, register_group,
    registration_cloud, rotation_deg)

_NONE = np.zeros(0)  # an absent array argument of the compiled kernels
GROUP_SIZE = 3  # the paper's groups of three neighbouring scans
MAX_SKIPPED = 1000
#: ``build_map`` reads and prepares the scans ahead of registration in two threads. One was not
#: enough: small_gicp holds the GIL through each call (covariances, ICP: ~7 of 16 s of CPU on
#: the 250-scan benchmark), so a prepare thread only gets on while registration is between
#: calls, and registration waited for it 5 of 13 s. With two, one prepares while the other
#: waits for the GIL (registration then waited 2.4 s; 13.2 -> 11.9-12.4 s, same map).
PREPARE_WORKERS = 2
#: scans prepared ahead (~2 MB each): enough to keep both threads busy through the groups
PREPARE_AHEAD = 6


@dataclass
class MapBuildParams:
    """Map building parameters (``config/map_builder.yaml`` style, dotted for nested)."""

    d_max: float = 60.0  # drop points farther from the sensor, metres
    d_min: float = 0.0  # drop points closer (e.g. hits on the vehicle), metres
    voxel: float = 0.1  # map voxel size, applied to every scan and at every merge, metres
    icp: bool = True  # False: accumulate with the given poses only
    remove_dynamic: bool = True
    corridor: float = 0.0  # > 0: remove dynamic classes only this close to the path (metres)
    crop_radius: float = 0.0  # > 0: keep points within this horizontal radius of crop_center
    crop_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    crop_margin: float = 5.0  # scans are cropped this much wider (ICP may move them)
    max_scans: int = 0  # > 0: the map is full after this many scans
    pose_tolerance: float = 0.02  # seconds a scan may lie beyond the pose stream
    vertical_angle_deg: float = 0.0  # elevation correction of every point (KITTI HDL-64E: 0.205)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    deskew: DeskewParams = field(default_factory=lambda: DeskewParams(source="field"))

    def __post_init__(self) -> None:
        if not self.d_max > 0 or self.d_min < 0 or self.d_min >= self.d_max:
            raise ValueError(f"need 0 <= d_min < d_max, got d_min={self.d_min}, "
                             f"d_max={self.d_max}")
        if not self.voxel > 0:
            raise ValueError(f"voxel size must be positive, got {self.voxel}")
        if self.corridor < 0 or self.crop_radius < 0 or self.max_scans < 0:
            raise ValueError("corridor, crop_radius and max_scans must not be negative")
        if len(tuple(self.crop_center)) != 3:
            raise ValueError("crop_center must be [x, y, z]")


class ScanRejected(ValueError):
    """A scan the builder refused; ``kind`` says why. The map built so far is untouched."""

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.kind = kind  # fields | pose | order | empty | full | load


@dataclass(frozen=True)
class ScanReport:
    """What happened to one accepted scan."""

    index: int  # position among accepted scans
    points_in: int
    points_kept: int  # after range filter, voxel grid, dynamic removal and crop
    merges: int  # groups registered because this scan completed them
    seconds: float


@dataclass
class PreparedScan:
    """A scan ready to join the map (:meth:`StreamingMapBuilder.prepare_scan`)."""

    scan_id: str
    stamp: float
    lidar: np.ndarray  # 4x4 lidar pose in the map frame, as given
    points_in: int
    kept: LabelledCloud  # map frame: de-skewed, filtered, voxel grid with majority labels
    reg: RegistrationCloud | None  # ICP grids (None with ICP off)
    deskewed: bool
    seconds: dict[str, float]  # per stage


@dataclass
class MapBuildResult:
    """The map and what building it did."""

    map: LabelledCloud
    scan_ids: list[str]
    stamps: np.ndarray  # (N,) of accepted scans
    prior_poses: np.ndarray  # (N, 4, 4) lidar in map, as given
    corrections: np.ndarray  # (N, 4, 4) applied on the left: refined = correction @ prior
    skipped: list[tuple[str, str]]  # (scan id, reason)
    timings: dict[str, float]
    points_in: int
    points_kept: int
    pairs: list[PairResult]

    @property
    def refined_poses(self) -> np.ndarray:
        return self.corrections @ self.prior_poses

    def pose_changes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per scan: how far ICP moved the lidar (metres) and turned it (degrees)."""
        refined = self.refined_poses
        shift = np.linalg.norm(refined[:, :3, 3] - self.prior_poses[:, :3, 3], axis=1)
        angle = np.array([rotation_deg(c) for c in self.corrections])
        return shift, angle


@dataclass
class _Node:
    """A cloud waiting in the stack: its map-frame points and the scans it holds."""

    pending: LabelledCloud | Future  # a merged group's cloud is voxelized in the merge thread
    scans: np.ndarray  # indices of accepted scans
    reg: RegistrationCloud | None = None  # what ICP works on (None with ICP off)

    @property
    def cloud(self) -> LabelledCloud:
        if isinstance(self.pending, Future):
            self.pending = self.pending.result()
        return self.pending


def _merged_cloud(nodes: list[_Node], corrections: list[np.ndarray], voxel: float,
                  seconds: list[float] | None = None) -> LabelledCloud:
    """The voxel grid (majority labels) of the nodes' clouds moved by their corrections; the
    time it took is appended to ``seconds``."""
    start = time.perf_counter()
    parts = [filters.transform(n.cloud, c) if not np.allclose(c, np.eye(4), atol=1e-12)
             else n.cloud for n, c in zip(nodes, corrections)]
    cloud = filters.voxel_downsample(filters.concatenate(parts), voxel)
    if seconds is not None:
        seconds.append(time.perf_counter() - start)
    return cloud


class StreamingMapBuilder:
    """Scans in time order, one at a time; see the module docstring for the scheme."""

    def __init__(self, params: MapBuildParams | None = None,
                 lidar_extrinsic: np.ndarray | None = None,
                 mapping: LabelMapping | None = None,
                 dynamic_ids: np.ndarray | None = None) -> None:
        self.params = params or MapBuildParams()
        self.extrinsic = np.eye(4) if lidar_extrinsic is None else as_matrix(
            lidar_extrinsic, "lidar extrinsic")
        if dynamic_ids is None:
            dynamic_ids = (mapping or LabelMapping()).dynamic_kitti_ids()
        self.dynamic_ids = np.asarray(dynamic_ids, dtype=np.uint16)
        self.poses = PoseStream(tolerance=self.params.pose_tolerance)
        self._merger: ThreadPoolExecutor | None = None  # voxel grids of merged groups
        self.reset()

    # --- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all scans, poses and the map."""
        self._levels: list[list[_Node]] = []
        self._ids: list[str] = []
        self._stamps: list[float] = []
        self._priors: list[np.ndarray] = []
        self._corrections: list[np.ndarray] = []
        self._pairs: list[PairResult] = []
        # (scan id, reason) of refused scans; the newest MAX_SKIPPED only, so a live stream of
        # bad scans cannot grow memory
        self.skipped: deque[tuple[str, str]] = deque(maxlen=MAX_SKIPPED)
        # seconds per stage: de-skew (+ range filter and the move into the map frame, one pass),
        # filter (voxel grid with majority labels, dynamic classes, crop), grids (ICP grids of
        # each scan), covariances (k-d trees and covariances of ICP clouds), icp (pairwise ICP
        # and pose graphs), merge (grids and voxel grid of merged groups)
        self.timings = {"deskew": 0.0, "filter": 0.0, "grids": 0.0, "covariances": 0.0,
                        "icp": 0.0, "merge": 0.0}
        self._merge_seconds: list[float] = []  # voxel grids done in the merge thread
        self.points_in = 0
        self.points_kept = 0
        self.deskewed = 0  # scans motion-compensated
        self._offered = 0  # add_scan calls, accepted or not (default scan ids)
        self.poses.clear()

    @property
    def scan_count(self) -> int:
        return len(self._ids)

    @property
    def is_full(self) -> bool:
        return 0 < self.params.max_scans <= self.scan_count

    def path_xy(self) -> np.ndarray:
        """Horizontal lidar positions of the accepted scans (the vehicle path)."""
        if not self._priors:
            return np.zeros((0, 2))
        return np.array([p[:2, 3] for p in self._priors])

    # --- input ---------------------------------------------------------------------------
    def add_pose(self, stamp: float, pose: Any) -> None:
        """A pose of the vehicle (or lidar) for scans that come without one."""
        self.poses.add(stamp, pose)

    def add_scan(self, cloud: Any, pose: Any = None, stamp: float = 0.0,
                 scan_id: str | None = None, twist: np.ndarray | None = None) -> ScanReport:
        """Add one scan (lidar frame); ``pose`` None looks it up in the pose stream at ``stamp``.

        With de-skew on (``params.deskew``) and per-point times (a ``t``/``time``/``timestamp``
        field, or the azimuth with ``deskew.source`` azimuth/auto), the points are moved into the
        lidar frame of ``stamp`` first, with ``twist`` (the lidar's body velocity, per second) or
        else the velocity from the pose stream around ``stamp`` or from the previous scan's pose.

        Raises :class:`ScanRejected` with a message naming the problem (no x/y/z, no pose for its
        time, out of time order, empty after filtering, map full); nothing is changed then.
        """
        self._offered += 1
        scan_id = str(self._offered - 1) if scan_id is None else str(scan_id)
        try:
            return self.add_prepared(self.prepare_scan(cloud, pose, stamp, scan_id, twist))
        except ScanRejected as exc:
            self.skipped.append((scan_id, str(exc)))
            raise

    def prepare_scan(self, cloud: Any, pose: Any = None, stamp: float = 0.0,
                     scan_id: str = "", twist: np.ndarray | None = None,
                     path_xy: np.ndarray | None = None, use_previous: bool = True
                     ) -> PreparedScan:
        """The per-scan half of :meth:`add_scan` (checks, de-skew, filters, ICP grids), which
        changes nothing: :func:`build_map` runs it for the next scan in a second thread while
        this one registers (its compiled kernels and numpy release the GIL).

        ``path_xy``: the vehicle path for dynamic removal in a corridor (default: the accepted
        scans' and this one); ``use_previous`` False: no velocity from the previous accepted
        scan (whose pose another thread may be adding)."""
        t0 = time.perf_counter()
        p = self.params
        stamp = float(stamp)
        if self.is_full:
            raise ScanRejected(f"scan {scan_id}: map is full ({p.max_scans} scans)", "full")
        try:
            scan = filters.as_scan_cloud(cloud, f"scan {scan_id}")
        except ValueError as exc:
            raise ScanRejected(str(exc), "fields") from None
        try:
            vehicle = self.poses.at(stamp) if pose is None else as_matrix(pose)
        except ValueError as exc:
            raise ScanRejected(f"scan {scan_id}: {exc}", "pose") from None
        lidar = vehicle @ self.extrinsic
        t1 = time.perf_counter()
        xyz, label, intensity, deskewed = self._prepare(scan, stamp, lidar, pose is None, twist,
                                                        scan_id, use_previous)
        t2 = time.perf_counter()
        if path_xy is None:
            path_xy = np.vstack([self.path_xy(), lidar[None, :2, 3]])
        kept = self._filter_scan(xyz, label, path_xy, intensity)
        if len(kept) == 0:
            raise ScanRejected(f"scan {scan_id}: no points left after filtering ({len(scan)} in, "
                               f"d_max {p.d_max} m"
                               + (f", crop {p.crop_radius} m" if p.crop_radius > 0 else "") + ")",
                               "empty")
        t3 = time.perf_counter()
        reg = (registration_cloud(kept.xyz, lidar[:3, 3], p.registration) if p.icp else None)
        t4 = time.perf_counter()
        return PreparedScan(scan_id, stamp, lidar, len(scan), kept, reg, deskewed,
                            {"deskew": t2 - t1, "filter": (t1 - t0) + (t3 - t2),
                             "grids": t4 - t3})

    def add_prepared(self, prepared: PreparedScan) -> ScanReport:
        """The map half of :meth:`add_scan`: the scan joins the stack (groups that it completes
        are registered and merged). Raises :class:`ScanRejected` (map full, out of time order);
        nothing is changed then."""
        t0 = time.perf_counter()
        p, scan_id, stamp = self.params, prepared.scan_id, prepared.stamp
        if self.is_full:
            raise ScanRejected(f"scan {scan_id}: map is full ({p.max_scans} scans)", "full")
        if self._stamps and stamp < self._stamps[-1]:
            raise ScanRejected(f"scan {scan_id} at {stamp:.6f} s is older than the previous "
                               f"scan ({self._stamps[-1]:.6f} s); scans must be in time order",
                               "order")
        index = len(self._ids)
        self._ids.append(scan_id)
        self._stamps.append(stamp)
        self._priors.append(prepared.lidar)
        self._corrections.append(np.eye(4))
        self.points_in += prepared.points_in
        self.points_kept += len(prepared.kept)
        self.deskewed += int(prepared.deskewed)
        for key, seconds in prepared.seconds.items():
            self.timings[key] += seconds
        merges = self._push(_Node(prepared.kept, np.array([index]), prepared.reg), 0)
        return ScanReport(index, prepared.points_in, len(prepared.kept), merges,
                          sum(prepared.seconds.values()) + time.perf_counter() - t0)

    def _prepare(self, scan: LabelledCloud, stamp: float, lidar: np.ndarray, from_stream: bool,
                 twist: np.ndarray | None, scan_id: str, use_previous: bool = True
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, bool]:
        """The scan's points within range, de-skewed into the lidar frame of ``stamp``
        (docs/mapping.md, De-skew) after the elevation correction, in the map frame; and their
        labels and intensity (None when the scan has none: the map then has none). One
        compiled pass (``kernels.prepare_points``); no de-skew without per-point time or a
        velocity."""
        p = self.params
        xyz = scan.xyz
        if p.vertical_angle_deg != 0:
            xyz = correct_vertical_angle(xyz, p.vertical_angle_deg)
        d = p.deskew
        times, azimuth = None, _NONE
        if d.enabled and d.source != "none":
            if d.source in ("auto", "field") and any(k in scan.extra for k in TIME_FIELDS):
                try:
                    times = point_times(xyz, scan.extra, d)
                except ValueError as exc:
                    raise ScanRejected(f"scan {scan_id}: {exc}", "fields") from None
            elif d.source in ("auto", "azimuth"):
                sign = -1.0 if d.direction == "clockwise" else 1.0
                azimuth = np.array([np.radians(d.reference_azimuth_deg), sign, d.period])
        if (times is not None or len(azimuth)) and twist is None:
            twist = self._velocity(stamp, lidar, from_stream, use_previous)
        if times is None and not len(azimuth):
            twist = None
        if twist is None:
            times, azimuth = None, _NONE
        points = xyz if xyz.dtype in (np.float32, np.float64) else xyz.astype(np.float64)
        out, keep = kernels.prepare_points(
            np.ascontiguousarray(points), _NONE if times is None else times,
            _NONE if twist is None else np.asarray(twist, np.float64),
            np.ascontiguousarray(lidar, dtype=np.float64), float(p.d_min), float(p.d_max),
            azimuth)
        intensity = scan.extra.get("intensity")
        return (out, None if scan.label is None else scan.label[keep],
                None if intensity is None else np.asarray(intensity, np.float32)[keep],
                twist is not None)

    def _velocity(self, stamp: float, lidar: np.ndarray, from_stream: bool,
                  use_previous: bool = True) -> np.ndarray | None:
        """The lidar's body twist at ``stamp``: from the pose stream half a sweep either side,
        else from the previous scan's pose (within ``deskew.max_gap``)."""
        half = self.params.deskew.period / 2
        if from_stream:
            try:
                before = self.poses.at(stamp - half) @ self.extrinsic
                after = self.poses.at(stamp + half) @ self.extrinsic
                return body_twist(before, after, 2 * half)
            except ValueError:
                pass
        if use_previous and self._priors and \
                0 < stamp - self._stamps[-1] <= self.params.deskew.max_gap:
            return body_twist(self._priors[-1], lidar, stamp - self._stamps[-1])
        return None

    def _filter_scan(self, xyz: np.ndarray, label: np.ndarray | None, path_xy: np.ndarray,
                     intensity: np.ndarray | None = None) -> LabelledCloud:
        """Voxel grid (majority label; intensity: the mean over the voxel's points of that
        label), dynamic classes, crop: the scan's share of the map."""
        p = self.params
        extra = {} if intensity is None else {"intensity": intensity}
        cloud = filters.voxel_downsample(LabelledCloud(xyz, label, extra), p.voxel)
        if cloud.label is None:
            cloud = LabelledCloud(cloud.xyz, np.full(len(cloud), filters.UNLABELED, np.uint16),
                                  cloud.extra)
        if p.remove_dynamic:
            cloud = self._remove_dynamic(cloud, path_xy)
        if p.crop_radius > 0:
            cloud = filters.crop_radius(cloud, np.asarray(p.crop_center),
                                        p.crop_radius + p.crop_margin)
        return cloud

    def _remove_dynamic(self, cloud: LabelledCloud, path_xy: np.ndarray) -> LabelledCloud:
        corridor = self.params.corridor if self.params.corridor > 0 else None
        return filters.remove_dynamic(cloud, self.dynamic_ids, path_xy, corridor)

    # --- the stack -----------------------------------------------------------------------
    def _push(self, node: _Node, level: int) -> int:
        merges = 0
        while True:
            while len(self._levels) <= level:
                self._levels.append([])
            self._levels[level].append(node)
            if len(self._levels[level]) < GROUP_SIZE:  # >= after a failed merge: retried
                return merges
            node, updates = self._merge(self._levels[level])  # may raise: nothing changed yet
            self._commit(updates)
            self._levels[level] = []
            merges += 1
            level += 1

    def _commit(self, updates: list[tuple[np.ndarray, np.ndarray]]) -> None:
        for scans, correction in updates:
            for s in scans:
                self._corrections[s] = correction @ self._corrections[s]

    def _merge(self, group: list[_Node]) -> tuple[_Node, list[tuple[np.ndarray, np.ndarray]]]:
        """Register a time-ordered group (multiway ICP), merge it, voxel-downsample it.

        Returns the merged node and the corrections to commit for its scans; the builder's state
        is only changed by the caller, so a failure here loses nothing.
        """
        p = self.params
        t0 = time.perf_counter()
        corrections = [np.eye(4)] * len(group)
        weights = [len(n.scans) for n in group]
        reg = None
        covariances = merged = 0.0
        if p.icp and all(n.reg is not None for n in group):
            for node in group[1:]:  # the targets of the group's edges
                node.reg.target(p.registration)
            for node in group[:-1]:  # and their sources
                node.reg.source(p.registration)
            covariances = time.perf_counter() - t0
            result = register_group([n.reg for n in group], weights, p.registration)
            corrections = result.corrections
            self._pairs.extend(result.pairs)
            tm = time.perf_counter()
            reg = merge_registration([n.reg for n in group], corrections, weights,
                                     p.registration)
            merged = time.perf_counter() - tm
        t1 = time.perf_counter()
        updates = [(node.scans, c) for node, c in zip(group, corrections)
                   if not np.allclose(c, np.eye(4), atol=1e-12)]
        if p.remove_dynamic and p.corridor > 0:  # needs the path now: here
            cloud = self._remove_dynamic(_merged_cloud(group, corrections, p.voxel),
                                         self.path_xy())
        else:  # the voxel grid of the merged cloud in the merge thread (compiled, GIL-free)
            # while this one registers the next groups; FIFO: its inputs are done before it
            if self._merger is None:
                self._merger = ThreadPoolExecutor(max_workers=1, thread_name_prefix="merge")
            cloud = self._merger.submit(_merged_cloud, list(group), corrections, p.voxel,
                                        self._merge_seconds)
        self.timings["covariances"] += covariances
        self.timings["icp"] += t1 - t0 - covariances - merged
        self.timings["merge"] += time.perf_counter() - t1 + merged
        return _Node(cloud, np.concatenate([n.scans for n in group]), reg), updates

    def _final_filters(self, cloud: LabelledCloud) -> LabelledCloud:
        p = self.params
        if p.remove_dynamic and p.corridor > 0:
            cloud = self._remove_dynamic(cloud, self.path_xy())
        if p.crop_radius > 0:
            cloud = filters.crop_radius(cloud, np.asarray(p.crop_center), p.crop_radius)
        return cloud

    def current_map(self) -> LabelledCloud:
        """The map of all scans so far, without registering the groups not yet complete.

        Cheap and non-destructive (for publishing while driving); :meth:`finish` registers the
        rest.
        """
        nodes = [n for level in self._levels for n in level]
        if not nodes:
            return LabelledCloud(np.zeros((0, 3)), np.zeros(0, np.uint16))
        if len(nodes) == 1:
            cloud = nodes[0].cloud
        else:
            cloud = filters.voxel_downsample(filters.concatenate([n.cloud for n in nodes]),
                                             self.params.voxel)
        return self._final_filters(cloud)

    def finish(self) -> MapBuildResult:
        """Register what waits on the levels until one cloud remains; the result so far.

        Scans may still be added afterwards; they join as the latest part of the map.
        """
        carry: _Node | None = None
        updates: list[tuple[np.ndarray, np.ndarray]] = []
        for level in range(len(self._levels)):
            items = self._levels[level] + ([carry] if carry is not None else [])
            if len(items) > 1:
                carry, done = self._merge(items)
                updates += done
            elif items:
                carry = items[0]
        if carry is not None:  # only now change the state: a failed merge above loses nothing
            self._commit(updates)
            self._levels = [[] for _ in self._levels[:-1]] + [[carry]]
        return self.result()

    def result(self) -> MapBuildResult:
        n = len(self._ids)
        return MapBuildResult(
            map=self.current_map(), scan_ids=list(self._ids), stamps=np.array(self._stamps),
            prior_poses=np.array(self._priors).reshape(n, 4, 4),
            corrections=np.array(self._corrections).reshape(n, 4, 4),
            skipped=list(self.skipped),
            timings={**self.timings, "merge": self.timings["merge"] + sum(self._merge_seconds)},
            points_in=self.points_in,
            points_kept=self.points_kept, pairs=list(self._pairs))


@dataclass
class ScanInput:
    """One scan for :func:`build_map`: the cloud (or a loader, so scans are read one by one)."""

    cloud: LabelledCloud | Callable[[], Any]
    pose: np.ndarray
    stamp: float
    scan_id: str = ""


def build_map(scans: Iterable[ScanInput], params: MapBuildParams | None = None,
              lidar_extrinsic: np.ndarray | None = None, mapping: LabelMapping | None = None,
              progress: bool = False) -> MapBuildResult:
    """Build a map from scans (sorted by time here); bad scans are skipped and reported.

    Loaders (``ScanInput.cloud`` callables) run in ``PREPARE_WORKERS`` threads, two scans at a
    time: each must read its own scan (a file per scan is)."""
    from tqdm import tqdm

    t0 = time.perf_counter()
    items = sorted(scans, key=lambda s: s.stamp)
    builder = StreamingMapBuilder(params, lidar_extrinsic, mapping)
    twists: list[np.ndarray | None] = [None] * len(items)
    p = builder.params
    if p.deskew.enabled and p.deskew.source != "none" and len(items) > 1:
        try:  # central differences: the velocity at each scan, not the one before it
            lidar = np.array([as_matrix(item.pose) @ builder.extrinsic for item in items])
            stamps = np.array([item.stamp for item in items], float)
            if np.all(np.diff(stamps) > 0):
                twists = twists_from_poses(lidar, stamps, p.deskew.max_gap)
        except ValueError:
            pass  # a bad pose is reported by add_scan
    path = np.zeros((len(items), 2))  # the vehicle path as given (dynamic removal corridor)
    for i, item in enumerate(items):
        try:
            path[i] = (as_matrix(item.pose) @ builder.extrinsic)[:2, 3]
        except ValueError:
            path[i] = path[i - 1] if i else 0.0  # a bad pose is reported by prepare_scan
    loads = [0.0] * len(items)

    def prepare(i: int) -> PreparedScan:
        """Scan i read and prepared (runs in the second thread)."""
        item, scan_id = items[i], items[i].scan_id or str(i)
        tl = time.perf_counter()
        try:
            cloud = item.cloud() if callable(item.cloud) else item.cloud
        except (OSError, ValueError) as exc:
            raise ScanRejected(f"scan {scan_id}: {exc}", "load") from None
        finally:
            loads[i] = time.perf_counter() - tl
        return builder.prepare_scan(cloud, item.pose, item.stamp, scan_id, twists[i],
                                    path_xy=path[:i + 1], use_previous=False)

    # the next scans are read and prepared while this one registers: two cores at work
    bar = tqdm(total=len(items), desc="scans", unit="scan", disable=not progress, leave=False)
    with ThreadPoolExecutor(max_workers=PREPARE_WORKERS, thread_name_prefix="prepare") as pool:
        ahead = deque(pool.submit(prepare, i) for i in range(min(PREPARE_AHEAD, len(items))))
        for i in range(len(items)):
            current = ahead.popleft()
            if i + PREPARE_AHEAD < len(items):
                ahead.append(pool.submit(prepare, i + PREPARE_AHEAD))
            try:
                builder.add_prepared(current.result())
            except ScanRejected as exc:
                builder.skipped.append((items[i].scan_id or str(i), str(exc)))
            bar.update()
            bar.set_postfix(kept=builder.points_kept, skipped=len(builder.skipped))
    bar.close()
    load = sum(loads)
    tf = time.perf_counter()
    result = builder.finish()
    result.timings["load"] = load
    result.timings["finish"] = time.perf_counter() - tf
    result.timings["total"] = time.perf_counter() - t0
    return result
