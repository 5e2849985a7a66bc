"""The live map's worker, without ROS: scans and poses in, the labelled map out.

``map_builder`` (semcal_ros/ros/nodes/map_builder.py) wires this to its topics, services and
diagnostics; everything that decides lives here:

* arrivals (:meth:`LiveMap.arrive`, :meth:`LiveMap.clock`) only queue: scans wait for a pose at or
  after their stamp (:class:`~semcal_ros.mapping.time_matching.ScanPoseMatcher`, bounded queue),
  time going back is told apart from strays and resets the map when sustained;
* a worker thread of its own builds the ready scans, one prepared ahead: while a scan registers
  (small_gicp holds the GIL), the next one is converted, de-skewed and filtered in the prepare
  thread (compiled kernels and numpy release it), so a slow registration never blocks arrivals;
* the map is handed to ``publish`` at most every ``publish_period`` s while it changes;
* :class:`WorkClock`: the worker's seconds per scan, amortised, against the lidar's budget.

The scan messages are queued as they came (the most compact form a scan has) and turned into
clouds by ``convert`` in the prepare thread.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud, finite_rows
from semcal_ros.engine.pose import Pose
from semcal_ros.mapping import MapBuildParams, ScanRejected, StreamingMapBuilder
from semcal_ros.mapping.builder import PreparedScan
from semcal_ros.mapping.time_matching import MatchNote, NoteKind, Reset, ScanPoseMatcher


@dataclass
class LiveMapParams:
    """The map builder node's parameters; the builder's own are ``mapping.*``
    (:class:`~semcal_ros.mapping.MapBuildParams`)."""

    map_frame: str = ""  # frame id of the published map (empty: the poses' frame)
    # Lidar in the vehicle frame when poses are of the vehicle: x, y, z, qx, qy, qz, qw.
    lidar_extrinsic: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    require_labels: bool = True  # refuse scans without a 'label' field (segment them first)
    publish_period: float = 2.0  # s between map publications while the map changes
    queue_size: int = 50  # scans waiting for their pose or for the builder (oldest dropped)
    reset_on_time_jump: bool = True
    time_jump: float = 1.0  # s a message may be older than its stream's newest before it is behind
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
class Counts:
    received: int = 0
    accepted: int = 0
    dropped_no_pose: int = 0  # older than every pose kept
    ignored_full: int = 0
    resets: int = 0
    rejected: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Status:
    """The diagnostics of the live map: ``warn`` (else OK), the line and the values."""

    warn: bool
    message: str
    values: dict[str, Any]


class LiveMap:
    """The map of a live scan and pose stream, built by a worker thread of its own.

    ``convert(scan)`` turns a queued scan message into a :class:`LabelledCloud` (prepare
    thread); ``publish(cloud)`` hands the map on (worker thread); ``warn(text)`` logs a refusal
    or a reset; ``pose_topics`` names where poses come from, for the waiting note.
    """

    def __init__(self, params: LiveMapParams, convert: Callable[[Any], LabelledCloud],
                 publish: Callable[[LabelledCloud], None], warn: Callable[[str], None],
                 pose_topics: str = "'odom' or 'pose'") -> None:
        self.params = params
        self._convert, self._publish, self._warn = convert, publish, warn
        self.builder = StreamingMapBuilder(params.mapping, params.extrinsic())
        self.counts = Counts()
        self.last_error = ""
        self.last_reset = ""
        self._wake = threading.Condition()
        self._builder_lock = threading.Lock()
        self._dirty = False
        self._last_publish = 0.0
        self._stop = False
        # scans wait for their poses; time going back: strays vs jumps (under _wake)
        self.matcher = ScanPoseMatcher(params.time_jump, params.jump_confirm,
                                       params.reset_on_time_jump, params.queue_size,
                                       params.mapping.pose_tolerance, pose_topics)
        self.published = (0, 0)  # (points, scans) of the last map published
        self.clock_work = WorkClock(params.budget_window)  # the worker's seconds per scan
        self._prepare_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="prepare")
        self._worker = threading.Thread(target=self._work, name="map_builder", daemon=True)

    def start(self) -> None:
        self._worker.start()

    def close(self) -> None:
        """Stop the worker (after the pass it is in) and the prepare thread."""
        self._wake_worker(stop=True)
        self._worker.join(timeout=5.0)
        self._prepare_pool.shutdown(wait=False)

    def _wake_worker(self, stop: bool = False) -> None:
        with self._wake:
            self._stop = self._stop or stop
            self._wake.notify()

    # --- arrivals: queue only -----------------------------------------------------------------
    def arrive(self, kind: str, stamp: float, item: Any) -> None:
        """Queue a scan (``kind`` "scan") or pose ("pose"); the matcher decides: queued, held
        back, stray."""
        with self._wake:
            notes = self.matcher.arrive(kind, stamp, item, time.monotonic())
            self._wake.notify()
        self._note(notes)

    def clock(self, stamp: float) -> None:
        """``/clock`` going back by more than ``time_jump`` is a jump at once (a simulator or
        a looping player said so)."""
        with self._wake:
            notes = self.matcher.clock(stamp, time.monotonic())
            self._wake.notify()
        self._note(notes)

    def _note(self, notes: list[MatchNote]) -> None:
        for note in notes:
            self.rejected("queue" if note.kind is NoteKind.QUEUE_FULL else "stray", note.text)

    def rejected(self, kind: str, text: str) -> None:
        """Count a refusal of ``kind`` and log it (once while the same text repeats)."""
        self.counts.rejected[kind] = self.counts.rejected.get(kind, 0) + 1
        if text != self.last_error:
            self._warn(text)
        self.last_error = text

    # --- the worker -----------------------------------------------------------------------------
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
                self.maybe_publish()
            except Exception as exc:  # noqa: BLE001 - keep building; say what went wrong
                self.rejected("internal", f"map builder error: {type(exc).__name__}: {exc}")

    def _add_pose(self, stamp: float, pose: Pose) -> None:
        span = self.builder.poses.span()
        if span is not None and stamp < span[1]:
            self.rejected("pose_order", f"pose at {stamp:.3f} s is older than the previous one "
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
        self._warn(self.last_reset)
        self._reset_builder()

    def _next_scan(self) -> tuple[float, Any] | None:
        """The oldest queued scan once its pose can be interpolated (or never will be)."""
        with self._wake:
            return self.matcher.next_scan(self.builder.poses.span())

    def _drain_scans(self) -> None:
        """Build the ready scans, one prepared ahead. Each scan is charged the worker's time
        since the previous one was done (the rate the node keeps up with)."""
        mark = time.perf_counter()
        ahead = self._take_next()
        while ahead is not None:
            current, ahead = ahead, self._take_next()
            if self._add_prepared(*current):
                now = time.perf_counter()
                self.clock_work.scan(now - mark)
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
            if stamp < span[0] - self.params.mapping.pose_tolerance:
                self.counts.dropped_no_pose += 1  # older than every pose kept
                continue
            return stamp, self._prepare_pool.submit(self._prepare, stamp, msg)
        return None

    def _prepare(self, stamp: float, msg: Any) -> PreparedScan | str:
        """The scan converted and prepared (prepare thread), or why it is ignored."""
        cloud = self._convert(msg)
        if not np.any(finite_rows(cloud.xyz)):
            what = "has no points" if len(cloud) == 0 else \
                f"has only NaN or infinite points ({len(cloud)})"
            return f"scan at {stamp:.3f} s {what}; ignored"
        return self.builder.prepare_scan(cloud, None, stamp, f"{stamp:.3f}")

    def _add_prepared(self, stamp: float, future: Future) -> bool:
        """The prepared scan joins the map; False (counted, logged) when it cannot."""
        try:
            prepared = future.result()
            if isinstance(prepared, str):
                self.rejected("nan", prepared)
                return False
            self.builder.add_prepared(prepared)
        except ScanRejected as exc:
            self.builder.skipped.clear()  # counted here; the list would grow forever
            self.rejected(exc.kind, str(exc))
            return False
        except ValueError as exc:  # a message whose data does not match its layout
            self.rejected("fields", f"scan ignored: {exc}")
            return False
        self.counts.accepted += 1
        self._dirty = True
        return True

    def _reset_builder(self) -> None:
        self.builder.reset()
        self.clock_work.clear()
        self.counts.resets += 1
        self._dirty = True

    def maybe_publish(self, force: bool = False) -> None:
        """Hand the map to ``publish`` when it changed and ``publish_period`` has passed."""
        now = time.monotonic()
        if not (self._dirty or force) or (not force and now - self._last_publish
                                          < self.params.publish_period):
            return
        started = time.perf_counter()
        with self._builder_lock:
            cloud = self.builder.current_map()
            scans = self.builder.scan_count
            self._dirty = False
        self._publish(cloud)
        self._last_publish = now
        self.published = (len(cloud), scans)
        self.clock_work.charge(time.perf_counter() - started)

    # --- requests -------------------------------------------------------------------------------
    def snapshot(self, finish: bool) -> LabelledCloud:
        """The map as it is (``finish``: the builder's final pass first, e.g. for saving)."""
        with self._builder_lock:
            return self.builder.finish().map if finish else self.builder.current_map()

    def mark_changed(self) -> None:
        """The map changed outside the worker (a finishing pass): publish it again."""
        self._dirty = True

    def reset(self) -> int:
        """Start over by request: the map and the queue are dropped (published at once);
        returns the queued scans dropped."""
        with self._wake:
            dropped = self.matcher.clear()
        with self._builder_lock:
            self._reset_builder()
        self.maybe_publish(force=True)
        return dropped

    def status(self) -> Status:
        """What the diagnostics say: WARN while poses are missing, the worker falls behind the
        lidar, nothing was accepted or the queue overflowed; OK otherwise."""
        c, p = self.counts, self.params
        with self._wake:
            queued = len(self.matcher.scans)
            waiting = self.matcher.waiting_for_poses(time.monotonic())
            dropped_queue, strays = self.matcher.dropped_queue, self.matcher.strays
        values: dict[str, Any] = {
            "scans_received": c.received, "scans_accepted": c.accepted,
            "scans_queued": queued, "dropped_queue_full": dropped_queue,
            "dropped_no_pose": c.dropped_no_pose, "ignored_map_full": c.ignored_full,
            "resets": c.resets, "last_reset": self.last_reset or "none",
            "strays_dropped": strays, "map_points": self.published[0],
            "map_scans": self.published[1],
            "poses": len(self.builder.poses), "scans_deskewed": self.builder.deskewed,
            "last_error": self.last_error or "none",
            "seconds_per_scan": round(self.clock_work.per_scan(), 4),
            "scan_budget": p.scan_budget,
        }
        values.update({f"rejected.{k}": v for k, v in c.rejected.items()})
        if waiting:
            return Status(True, waiting, values)
        budget, spent = p.scan_budget, self.clock_work.per_scan()
        samples = len(self.clock_work.samples)
        if budget > 0 and spent > budget and samples >= min(5, p.budget_window):
            return Status(True, f"falling behind the lidar: {spent:.3f} s of work per scan over "
                                f"the last {samples} scans (budget {budget:.3f} s); {queued} "
                                "queued", values)
        if c.received and not c.accepted:
            return Status(True, self.last_error or "no scan accepted yet (waiting for poses?)",
                          values)
        if dropped_queue:
            return Status(True, f"{dropped_queue} scans dropped (queue full)", values)
        return Status(False, f"{c.accepted} scans in the map", values)


__all__ = ["Counts", "LiveMap", "LiveMapParams", "Status", "WorkClock"]
