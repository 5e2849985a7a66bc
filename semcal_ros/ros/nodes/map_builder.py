"""``map_builder``: labelled lidar scans + poses -> the labelled map, published on ``map``.

Inputs (relative names, remap them): ``scan`` (PointCloud2 with x, y, z and a ``label`` field of
SemanticKITTI ids; unlabelled scans go through ``cloud_segmenter`` first), and the lidar's (or,
with ``lidar_extrinsic``, the vehicle's) pose in the map frame on ``odom`` (nav_msgs/Odometry) or
``pose`` (geometry_msgs/PoseStamped). A scan gets its pose by interpolating the pose stream at the
scan's stamp, so a scan waits (bounded queue) until a pose at or after its stamp has arrived.
A scan with a per-point time field (``t``, ``time``, ``timestamp``: Ouster, Velodyne, Livox
drivers) is de-skewed with the pose stream's motion around its stamp (``mapping.deskew.*``;
diagnostics value ``scans_deskewed``).

The work happens in a thread of its own, so a slow registration never blocks the subscriptions:
callbacks only convert and enqueue. The map (x, y, z, label) is published on ``map`` (transient
local: a calibrator started later still gets it) at most every ``publish_period`` seconds while it
changes. Services: ``~/save_map`` (semcal_interfaces/SaveMap: PLY file) and ``~/reset``
(std_srvs/Trigger).

Time going back (a bag started over, a simulator reset) resets the map when
``reset_on_time_jump`` is set, but only when it is sustained: ``jump_confirm`` messages in a row
(scans or poses, in arrival order) more than ``time_jump`` s older than the newest one, or
``/clock`` going back by more than ``time_jump``. Fewer such messages are strays (a late packet, a
driver's bad stamp): they are dropped with a warning and the map stays. A reset is a warning in
the log and in the diagnostics (``resets``, ``last_reset``).
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from semcal_interfaces.srv import SaveMap
from semcal_ros.mapping import MapBuildParams, ScanRejected, StreamingMapBuilder
from semcal_ros.mapping.builder import PreparedScan
from semcal_ros.mapping.time_matching import Reset, ScanPoseMatcher
from semcal_ros.engine.pose import Pose
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.diagnostics import Diagnostics, Level
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import run_node


@dataclass
class MapBuilderNodeParams:
    """The node's own parameters; the builder's are ``mapping.*`` (MapBuildParams)."""

    map_frame: str = ""  # frame id of the published map (empty: the poses' frame)
    # Lidar in the vehicle frame when poses are of the vehicle: x, y, z, qx, qy, qz, qw.
    lidar_extrinsic: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    require_labels: bool = True  # refuse scans without a 'label' field (segment them first)
    publish_period: float = 2.0  # s between map publications while the map changes
    queue_size: int = 50  # scans waiting for their pose or for the builder (oldest dropped)
    reset_on_time_jump: bool = True
    time_jump: float = 1.0  # s a message may be older than the newest before it counts as behind
    jump_confirm: int = 3  # messages behind in a row that make a jump (fewer: strays, dropped)
    save_path: str = "map.ply"  # default file of ~/save_map
    diagnostics_period: float = 1.0  # s (0: off)
    scan_budget: float = 0.1  # s of work per scan, amortised, to keep up with the lidar (10 Hz:
    # 0.1); more over the last ``budget_window`` scans is a WARN (falling behind). 0: no check
    budget_window: int = 50  # scans the amortised time is taken over
    mapping: MapBuildParams = field(default_factory=MapBuildParams)

    def __post_init__(self) -> None:
        if len(self.lidar_extrinsic) != 7:
            raise ValueError("lidar_extrinsic must be [x, y, z, qx, qy, qz, qw]")
        if self.queue_size < 1 or self.publish_period <= 0:
            raise ValueError("queue_size must be >= 1 and publish_period > 0")
        if self.scan_budget < 0 or self.budget_window < 1:
            raise ValueError(f"scan_budget must be >= 0 s and budget_window >= 1, got "
                             f"{self.scan_budget}, {self.budget_window}")
        if not (self.time_jump > 0 and self.jump_confirm >= 1):
            raise ValueError(f"time_jump must be > 0 s and jump_confirm >= 1, got "
                             f"{self.time_jump}, {self.jump_confirm}")

    def extrinsic(self) -> np.ndarray:
        pose = Pose(np.array(self.lidar_extrinsic[:3]), np.array(self.lidar_extrinsic[3:]))
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = pose.rotation, pose.translation
        return matrix


class WorkClock:
    """The worker's busy seconds per scan over the last ``window`` scans, amortised: per scan the
    worker's time since the previous one was done while it had scans to build (conversion,
    de-skew, filters, registration when a group completes; the next scan is prepared beside
    it), plus the publications between scans, charged to the next scan. A live lidar at 10 Hz
    is kept up with while this stays under 0.1 s."""

    def __init__(self, window: int) -> None:
        self.samples: deque[float] = deque(maxlen=window)
        self.pending = 0.0  # work since the last scan (publications)

    def charge(self, seconds: float) -> None:
        self.pending += seconds

    def scan(self, seconds: float) -> None:
        self.samples.append(seconds + self.pending)
        self.pending = 0.0

    def clear(self) -> None:
        self.samples.clear()
        self.pending = 0.0

    def per_scan(self) -> float:
        return sum(self.samples) / len(self.samples) if self.samples else 0.0


@dataclass
class _Counts:
    received: int = 0
    accepted: int = 0
    dropped_no_pose: int = 0  # older than every pose kept
    ignored_full: int = 0
    resets: int = 0
    rejected: dict[str, int] = field(default_factory=dict)


class MapBuilderNode(Node):
    def __init__(self) -> None:
        super().__init__("map_builder")
        self.opts = declare_and_read(self, MapBuilderNodeParams())
        self.builder = StreamingMapBuilder(self.opts.mapping, self.opts.extrinsic())
        self.counts = _Counts()
        self.last_error = ""
        self.frame = self.opts.map_frame
        self._wake = threading.Condition()
        self._builder_lock = threading.Lock()
        self._dirty = False
        self._last_publish = 0.0
        self._last_stamp: float | None = None
        self._stop = False
        self.last_reset = ""
        # scans wait for their poses; time going back: strays vs jumps (under _wake). Scans are
        # queued as messages, converted by the worker (the most compact form a scan has)
        self.matcher = ScanPoseMatcher(
            self.opts.time_jump, self.opts.jump_confirm, self.opts.reset_on_time_jump,
            self.opts.queue_size, self.opts.mapping.pose_tolerance,
            f"'{self.resolve_topic_name('odom')}' or '{self.resolve_topic_name('pose')}'")
        self.published = (0, 0)  # (points, scans) of the last map published
        self.clock = WorkClock(self.opts.budget_window)  # the worker's seconds per scan
        self._prepare_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="prepare")

        overrides = qos.overridable()
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, "scan", self._on_scan, qos.sensor(10),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(Odometry, "odom", self._on_pose, qos.sensor(50),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(PoseStamped, "pose", self._on_pose, qos.sensor(50),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(Clock, "/clock", self._on_clock, qos.reliable(10),
                                 callback_group=inputs)
        self.map_pub = self.create_publisher(PointCloud2, "map", qos.latched(),
                                             qos_overriding_options=overrides)
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(SaveMap, "~/save_map", self._on_save, callback_group=services)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=services)
        self.diagnostics = Diagnostics(self, self._report, self.opts.diagnostics_period,
                                       callback_group=MutuallyExclusiveCallbackGroup())
        self._worker = threading.Thread(target=self._work, name="map_builder", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ready: scans on '{self.resolve_topic_name('scan')}', poses on "
            f"'{self.resolve_topic_name('odom')}' / '{self.resolve_topic_name('pose')}', map on "
            f"'{self.resolve_topic_name('map')}' (voxel {self.opts.mapping.voxel} m, "
            f"ICP {'on' if self.opts.mapping.icp else 'off'})")

    def close(self) -> None:
        with self._wake:
            self._stop = True
            self._wake.notify()
        self._worker.join(timeout=5.0)
        self._prepare_pool.shutdown(wait=False)

    # --- callbacks: convert and enqueue only ------------------------------------------------
    def _on_scan(self, msg: PointCloud2) -> None:
        self.counts.received += 1
        try:  # the layout is checked here, the points are read by the worker
            names = conv.pointcloud2_dtype(msg).names or ()
            missing = [n for n in ("x", "y", "z") if n not in names]
            if missing:
                raise ValueError(f"PointCloud2 has no {', '.join(missing)} field "
                                 f"(fields: {', '.join(names) or 'none'})")
            if self.opts.require_labels and "label" not in names:
                raise ValueError(f"PointCloud2 has no 'label' field (fields: {', '.join(names)}"
                                 f"); run cloud_segmenter first or set require_labels false")
        except ValueError as exc:
            self._rejected("fields", f"scan ignored: {exc}")
            return
        self._arrive("scan", conv.stamp_to_seconds(msg.header.stamp), msg)

    def _on_pose(self, msg: Any) -> None:
        try:
            stamp, pose, frame = conv.stamped_pose(msg)
        except ValueError as exc:
            self._rejected("pose", f"pose ignored: {exc}")
            return
        if not self.frame:
            self.frame = frame or "map"
        self._arrive("pose", stamp, pose)

    def _on_clock(self, msg: Clock) -> None:
        """``/clock`` going back by more than ``time_jump`` is a jump at once (a simulator or
        a looping player said so)."""
        with self._wake:
            notes = self.matcher.clock(conv.stamp_to_seconds(msg.clock), time.monotonic())
            self._wake.notify()
        self._note(notes)

    def _arrive(self, kind: str, stamp: float, item: Any) -> None:
        """Queue a scan or pose (:class:`ScanPoseMatcher` decides: queued, held back, stray)."""
        with self._wake:
            notes = self.matcher.arrive(kind, stamp, item, time.monotonic())
            self._wake.notify()
        self._note(notes)

    def _note(self, notes: list[str]) -> None:
        for text in notes:
            self._rejected("queue" if text.startswith("scans dropped") else "stray", text)

    def _rejected(self, kind: str, text: str) -> None:
        self.counts.rejected[kind] = self.counts.rejected.get(kind, 0) + 1
        if text != self.last_error:
            self.get_logger().warning(text)
        self.last_error = text

    # --- the worker -------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._wake:
                self._wake.wait(timeout=0.2)
                if self._stop:
                    return
                reset, poses = self.matcher.take()
            try:
                with self._builder_lock:
                    if reset is not None:
                        self._apply_reset(reset)
                    for stamp, pose in poses:
                        self._add_pose(stamp, pose)
                    self._drain_scans()
                self._maybe_publish()
            except Exception as exc:  # noqa: BLE001 - keep building; say what went wrong
                self._rejected("internal", f"map builder error: {type(exc).__name__}: {exc}")

    def _add_pose(self, stamp: float, pose: Pose) -> None:
        span = self.builder.poses.span()
        if span is not None and stamp < span[1]:
            self._rejected("pose_order", f"pose at {stamp:.3f} s is older than the previous one "
                                         f"({span[1]:.3f} s); ignored")
            return
        self.builder.add_pose(stamp, pose)

    def _apply_reset(self, reset: Reset) -> None:
        """Time went back: forget the map and the poses of the old pass (the worker, with the
        builder lock held)."""
        scans, points = self.builder.scan_count, self.published[0]
        self.last_reset = (f"time jumped back {reset.previous - reset.stamp:.1f} s "
                           f"({reset.reason}): map of "
                           f"{scans} scans ({points} points published) reset")
        self.get_logger().warning(self.last_reset)
        self._reset_builder()

    def _next_scan(self) -> tuple[float, PointCloud2] | None:
        """The oldest queued scan once its pose can be interpolated (or never will be)."""
        with self._wake:
            return self.matcher.next_scan(self.builder.poses.span())

    def _drain_scans(self) -> None:
        """Build the ready scans, one prepared ahead: while a scan registers (small_gicp holds
        the GIL), the next one is converted, de-skewed and filtered in the prepare thread
        (compiled kernels and numpy release it). Each scan is charged the worker's time since
        the previous one was done (the rate the node keeps up with)."""
        mark = time.perf_counter()
        ahead = self._take_next()
        while ahead is not None:
            current, ahead = ahead, self._take_next()
            if self._add_prepared(*current):
                now = time.perf_counter()
                self.clock.scan(now - mark)
                mark = now
            if ahead is None:  # one may have become ready meanwhile
                ahead = self._take_next()

    def _take_next(self) -> tuple[float, Future] | None:
        """The next ready scan, its preparation started; scans that cannot join are counted."""
        while (item := self._next_scan()) is not None:
            stamp, msg = item
            if self.builder.is_full:
                self.counts.ignored_full += 1
                continue
            span = self.builder.poses.span()
            if stamp < span[0] - self.opts.mapping.pose_tolerance:
                self.counts.dropped_no_pose += 1  # older than every pose kept
                continue
            return stamp, self._prepare_pool.submit(self._prepare, stamp, msg)
        return None

    def _prepare(self, stamp: float, msg: PointCloud2) -> PreparedScan | str:
        """The scan converted and prepared (prepare thread), or why it is ignored."""
        cloud = conv.pointcloud2_to_cloud(msg)
        if not np.any(np.all(np.isfinite(cloud.xyz), axis=1)):
            what = "has no points" if len(cloud) == 0 else \
                f"has only NaN or infinite points ({len(cloud)})"
            return f"scan at {stamp:.3f} s {what}; ignored"
        return self.builder.prepare_scan(cloud, None, stamp, f"{stamp:.3f}")

    def _add_prepared(self, stamp: float, future: Future) -> bool:
        """The prepared scan joins the map; False (counted, logged) when it cannot."""
        try:
            prepared = future.result()
            if isinstance(prepared, str):
                self._rejected("nan", prepared)
                return False
            self.builder.add_prepared(prepared)
        except ScanRejected as exc:
            self.builder.skipped.clear()  # counted here; the list would grow forever
            self._rejected(exc.kind, str(exc))
            return False
        except ValueError as exc:  # a message whose data does not match its layout
            self._rejected("fields", f"scan ignored: {exc}")
            return False
        self._last_stamp = stamp
        self.counts.accepted += 1
        self._dirty = True
        return True

    def _reset_builder(self) -> None:
        self.builder.reset()
        self.clock.clear()
        self._last_stamp = None
        self.counts.resets += 1
        self._dirty = True

    def _maybe_publish(self, force: bool = False) -> None:
        now = time.monotonic()
        if not (self._dirty or force) or (not force and now - self._last_publish
                                          < self.opts.publish_period):
            return
        started = time.perf_counter()
        with self._builder_lock:
            cloud = self.builder.current_map()
            scans = self.builder.scan_count
            self._dirty = False
        header = conv.make_header(self.frame or "map", self.get_clock().now().to_msg())
        self.map_pub.publish(conv.cloud_to_pointcloud2(cloud, header, extra_fields=False))
        self._last_publish = now
        self.published = (len(cloud), scans)
        self.clock.charge(time.perf_counter() - started)

    # --- services ---------------------------------------------------------------------------
    def _on_save(self, request: SaveMap.Request, response: SaveMap.Response) -> SaveMap.Response:
        from semcal_ros.io.ply import write_ply

        path = Path(request.path or self.opts.save_path).expanduser().resolve()
        try:
            with self._builder_lock:
                cloud = self.builder.finish().map if request.finish else \
                    self.builder.current_map()
            write_ply(path, cloud)
        except (OSError, ValueError) as exc:
            response.success, response.message = False, f"could not save the map: {exc}"
            return response
        if request.finish:
            self._dirty = True
        response.success, response.path, response.points = True, str(path), len(cloud)
        response.message = f"saved {len(cloud)} points to {path}"
        self.get_logger().info(response.message)
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        with self._wake:
            dropped = self.matcher.clear()
        with self._builder_lock:
            self._reset_builder()
        self._maybe_publish(force=True)
        response.success = True
        response.message = f"map reset ({dropped} queued scans dropped)"
        self.get_logger().info(response.message)
        return response

    # --- diagnostics ------------------------------------------------------------------------
    def _report(self) -> tuple[Level, str, dict[str, Any]]:
        c = self.counts
        with self._wake:
            queued = len(self.matcher.scans)
            waiting = self.matcher.waiting_for_poses(time.monotonic())
            dropped_queue, strays = self.matcher.dropped_queue, self.matcher.strays
        values = {
            "scans_received": c.received, "scans_accepted": c.accepted,
            "scans_queued": queued, "dropped_queue_full": dropped_queue,
            "dropped_no_pose": c.dropped_no_pose, "ignored_map_full": c.ignored_full,
            "resets": c.resets, "last_reset": self.last_reset or "none",
            "strays_dropped": strays, "map_points": self.published[0],
            "map_scans": self.published[1],
            "poses": len(self.builder.poses), "scans_deskewed": self.builder.deskewed,
            "last_error": self.last_error or "none",
            "seconds_per_scan": round(self.clock.per_scan(), 4),
            "scan_budget": self.opts.scan_budget,
        }
        values.update({f"rejected.{k}": v for k, v in c.rejected.items()})
        if waiting:
            return Level.WARN, waiting, values
        budget, spent = self.opts.scan_budget, self.clock.per_scan()
        if budget > 0 and spent > budget and len(self.clock.samples) >= min(
                5, self.opts.budget_window):
            return Level.WARN, (f"falling behind the lidar: {spent:.3f} s of work per scan over "
                                f"the last {len(self.clock.samples)} scans (budget "
                                f"{budget:.3f} s); {queued} queued"), values
        if c.received and not c.accepted:
            return Level.WARN, self.last_error or "no scan accepted yet (waiting for poses?)", \
                values
        if dropped_queue:
            return Level.WARN, f"{dropped_queue} scans dropped (queue full)", values
        return Level.OK, f"{c.accepted} scans in the map", values


def main(args: list[str] | None = None) -> int:
    return run_node(MapBuilderNode, threads=3, args=args)


if __name__ == "__main__":
    sys.exit(main())
