"""Scans matched to poses by time, and time going back told apart from a stray message.

A live scan carries a stamp but no pose; poses arrive on their own stream, at their own rate, in
arrival order. :class:`ScanPoseMatcher` holds the scans until a pose at or after their stamp has
arrived (so :class:`~semcal_ros.mapping.pose_stream.PoseStream` can interpolate instead of
extrapolating), at most ``queue_size`` of them (oldest dropped and counted), and says why scans
wait when the poses do not come.

Time going back (a bag started over, a simulator reset) is a reset of the map, but only when it is
sustained: ``jump_confirm`` messages in a row (scans or poses, in arrival order) each more than
``time_jump`` s older than the newest of its own stream, or ``/clock`` going back by more than
``time_jump``. Fewer such messages are strays (a late packet, a driver's bad stamp): dropped with
a note, the map stays. Each stream is held to its own newest stamp because one stream may run
seconds behind the other without time going back: on a loaded machine or a slow link a pose lost
on the wire and repaired by reliable delivery (on the writer's next heartbeat) holds back every
later pose until then, or the pose topic is matched later than the scans'; the poses then come in
a burst, old next to the scans but in order on their own stream. After a jump the queued
messages of the old pass are dropped, a reset is requested and the held-back messages of the new
pass are queued.

Pure bookkeeping without ROS or threads (the map builder node holds a lock around it), so every
rule is tested without DDS (test/test_mapping.py).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum
from typing import Any


class NoteKind(Enum):
    """What a note of :class:`ScanPoseMatcher` is about (the node counts them by this)."""

    STRAY = "stray"  # a message far behind the newest, not followed by enough others: dropped
    QUEUE_FULL = "queue"  # scans dropped from the full queue while poses do not come


@dataclass(frozen=True)
class MatchNote:
    """A note to log: its kind and the line to show."""

    kind: NoteKind
    text: str

    def __str__(self) -> str:
        return self.text


@dataclass(frozen=True)
class Reset:
    """Time went back: the map of the old pass is to be dropped."""

    previous: float  # newest stamp of the old pass
    stamp: float  # newest stamp of the new pass
    reason: str


class ScanPoseMatcher:
    def __init__(self, time_jump: float = 1.0, jump_confirm: int = 3,
                 reset_on_time_jump: bool = True, queue_size: int = 50,
                 pose_tolerance: float = 0.02, pose_topics: str = "'odom' or 'pose'") -> None:
        if not (time_jump > 0 and jump_confirm >= 1 and queue_size >= 1):
            raise ValueError(f"time_jump must be > 0 s, jump_confirm >= 1 and queue_size >= 1, "
                             f"got {time_jump}, {jump_confirm}, {queue_size}")
        self.time_jump, self.jump_confirm = time_jump, jump_confirm
        self.reset_on_time_jump, self.queue_size = reset_on_time_jump, queue_size
        self.pose_tolerance, self.pose_topics = pose_tolerance, pose_topics
        self.scans: deque[tuple[float, Any]] = deque()  # (stamp, scan) in arrival order
        self.poses: deque[tuple[float, Any]] = deque()  # for the builder to take
        self.newest: float | None = None  # newest stamp of a scan or pose
        self._newest_of: dict[str, float] = {}  # newest stamp of each stream ("scan", "pose")
        self._behind: list[tuple[str, float, Any]] = []
        self._last_clock: float | None = None
        self.reset: Reset | None = None  # requested, for the builder to apply first
        self.newest_pose: float | None = None
        self._pose_arrival: float | None = None  # monotonic
        self._queue_noted = -1e9
        self.strays = self.dropped_queue = 0

    # --- arrivals ---------------------------------------------------------------------------
    def arrive(self, kind: str, stamp: float, item: Any, now: float) -> list[MatchNote]:
        """Queue a scan (``kind`` "scan") or pose ("pose") that arrived at monotonic ``now``, or
        hold it back while it is far behind the newest stamp of its stream. Returns notes to log
        (strays dropped, scans dropped because the queue is full and poses are missing)."""
        own = self._newest_of.get(kind)
        if own is not None and stamp < own - self.time_jump:
            if not self.reset_on_time_jump:
                return [self._stray(kind, stamp, own, "reset_on_time_jump is false")]
            self._behind.append((kind, stamp, item))
            if len(self._behind) >= self.jump_confirm:
                return self._jump(f"{len(self._behind)} messages in a row more than "
                                  f"{self.time_jump:g} s older than the newest of their stream",
                                  max(s for _, s, _ in self._behind), now)
            return []
        notes = [self._stray(k, s, self._newest_of[k], f"time counts as jumped back after "
                                                       f"{self.jump_confirm} in a row")
                 for k, s, _ in self._behind]  # not sustained: strays
        self._behind = []
        self._newest_of[kind] = stamp if own is None else max(own, stamp)
        self.newest = stamp if self.newest is None else max(self.newest, stamp)
        return notes + self._enqueue(kind, stamp, item, now)

    def clock(self, stamp: float, now: float) -> list[MatchNote]:
        """``/clock``: going back by more than ``time_jump`` is a jump at once."""
        previous, self._last_clock = self._last_clock, stamp
        if previous is None or stamp >= previous - self.time_jump \
                or not self.reset_on_time_jump or self.newest is None:
            return []
        return self._jump(f"/clock went back from {previous:.3f} s to {stamp:.3f} s", stamp, now)

    def _stray(self, kind: str, stamp: float, newest: float, why: str) -> MatchNote:
        self.strays += 1
        return MatchNote(NoteKind.STRAY, f"{kind} at {stamp:.3f} s is {newest - stamp:.1f} s "
                                         f"older than the newest {kind} ({newest:.3f} s): dropped "
                                         f"({why})")

    def _jump(self, reason: str, newest: float, now: float) -> list[MatchNote]:
        previous = self.newest if self.newest is not None else newest
        self.scans.clear()
        self.poses.clear()
        self.reset = Reset(previous, newest, reason)
        self.newest = newest
        held, self._behind = self._behind, []
        self._newest_of = {}
        for kind, stamp, _ in held:
            self._newest_of[kind] = max(stamp, self._newest_of.get(kind, stamp))
        notes: list[MatchNote] = []
        for kind, stamp, item in held:
            notes += self._enqueue(kind, stamp, item, now)
        return notes

    def _enqueue(self, kind: str, stamp: float, item: Any, now: float) -> list[MatchNote]:
        if kind == "pose":
            self.poses.append((stamp, item))
            self.newest_pose, self._pose_arrival = stamp, now
            return []
        self.scans.append((stamp, item))
        notes: list[MatchNote] = []
        while len(self.scans) > self.queue_size:
            self.scans.popleft()
            self.dropped_queue += 1
            waiting = self.waiting_for_poses(now)
            if waiting and now - self._queue_noted > 5.0:  # not once per scan
                self._queue_noted = now
                notes.append(MatchNote(NoteKind.QUEUE_FULL,
                                       f"scans dropped (queue full): {waiting}"))
        return notes

    # --- the builder's side -----------------------------------------------------------------
    def take(self) -> tuple[Reset | None, list[tuple[float, Any]]]:
        """The reset to apply first (if any) and the poses that arrived since the last call."""
        reset, self.reset = self.reset, None
        poses, self.poses = list(self.poses), deque()
        return reset, poses

    def next_scan(self, span: tuple[float, float] | None) -> tuple[float, Any] | None:
        """The oldest queued scan once the poses (``span``: first and last pose stamp held by
        the builder) reach its stamp; None while it waits or a reset is due first."""
        if not self.scans or self.reset is not None:
            return None
        stamp = self.scans[0][0]
        if span is None or stamp > span[1] + self.pose_tolerance:
            return None  # its pose has not arrived yet
        return self.scans.popleft()

    def waiting_for_poses(self, now: float) -> str:
        """Why queued scans wait, when it is for poses that do not come ("" otherwise)."""
        if not self.scans:
            return ""
        newest_scan = self.scans[-1][0]
        if self.newest_pose is not None and newest_scan <= self.newest_pose + self.pose_tolerance:
            return ""
        if self.newest_pose is None:
            return (f"no pose received yet on {self.pose_topics}; {len(self.scans)} scans wait")
        age = now - (self._pose_arrival or 0.0)
        if age < 1.0:
            return ""
        return (f"no pose for {age:.1f} s (newest at {self.newest_pose:.3f} s, the newest scan "
                f"at {newest_scan:.3f} s): {len(self.scans)} scans wait for their poses; is "
                f"{self.pose_topics} publishing?")

    def clear(self) -> int:
        """Forget everything queued or held back (a reset by request); the scans dropped."""
        dropped = len(self.scans)
        self.scans.clear()
        self.poses.clear()
        self._behind = []
        self.reset = None
        return dropped


__all__ = ["MatchNote", "NoteKind", "Reset", "ScanPoseMatcher"]
