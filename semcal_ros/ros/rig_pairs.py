"""A moving rig's last N label image + labelled scan pairs, for one calibration over all of them.

A vehicle's camera and lidar share one extrinsic; one frame carries little evidence, several
frames of the drive together much more (docs/engine.md, "More evidence"). With the calibrator's
``rig_frames`` N > 1 the node also takes the lidar's labelled scans (``labelled_points``: the
cloud_segmenter's output, in the lidar frame), pairs each label image of a camera with the
scan nearest in stamp, and keeps the last N pairs per camera. A goal then calibrates the camera's
pose in the lidar frame against all N frames, each frame's map its own scan
(:class:`~semcal_ros.engine.frames.FrameSet`).

Pairing (:class:`RigPairs`, one per camera; the scans are shared, :class:`ScanBuffer`): a label
image waits until a scan at or after its stamp has arrived (scans arrive in stamp order, so no
later one can be nearer); then the nearest held scan within ``tolerance`` s is its partner. One
without a partner (every held scan farther than the tolerance, the scans it needed already
dropped from the buffer, or too many images waiting) is counted as unpaired with the reason,
never an error. Everything here is plain
Python, tested without DDS; the node only feeds it messages.

Bad input (a scan without a label field, without a frame id, with no finite point) is refused
with one line; the scans and pairs held are kept.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from semcal_ros.engine import validation
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import MOVING_KITTI
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.errors import InputError
from semcal_ros.mapping import MapBuildParams
from semcal_ros.ros.calibrate_goal import Request, checked_request, field_problems
from semcal_ros.ros.camera_inputs import LABELS, CameraInputs

#: The labelled scans' topic (relative): the cloud_segmenter's output name, so a calibrator and
#: a cloud_segmenter in one namespace connect without a remapping.
SCANS_TOPIC = "labelled_points"


@dataclass(frozen=True)
class Scan:
    """A labelled scan as held: its finite points (lidar frame), stamp and frame id."""

    stamp: float
    cloud: LabelledCloud
    frame_id: str


@dataclass(frozen=True)
class Pair:
    """One frame of the rig: a label image and the labelled scan nearest to it in stamp."""

    labels_stamp: float
    labels: np.ndarray
    scan: Scan

    @property
    def name(self) -> str:
        return f"labels {self.labels_stamp:.3f} s + scan {self.scan.stamp:.3f} s"


def usable_scan(cloud: LabelledCloud, stamp: float, frame_id: str) -> Scan:
    """A scan message's content as held: its finite points and labels (the frame's map is made
    from them when a goal needs it, :func:`frame_map`: a 10 Hz lidar would otherwise cost the
    input callbacks more than a core); :class:`InputError` naming what makes it unusable."""
    if not frame_id:
        raise InputError("the scan has no frame_id (its lidar frame is the result's parent "
                         "frame)")
    if cloud.label is None:
        raise InputError("the scan has no 'label' field (send it through cloud_segmenter)")
    finite = cloud.finite()
    if len(finite) == 0:
        raise InputError("the scan is empty" if len(cloud) == 0 else
                         f"the scan has no finite point ({len(cloud)} points)")
    return Scan(stamp, LabelledCloud(finite.xyz, finite.label), frame_id)


#: The map builder's ``mapping.d_max`` and ``mapping.voxel`` (one source with real-scene).
MAP_PARAMS = MapBuildParams()


def frame_map(scan: LabelledCloud, stamp: float = 0.0) -> LabelledCloud:
    """One frame's map from its labelled scan, in the scan's lidar frame, as ``semcal
    real-scene`` writes a one-scan scene's ``map.ply``: moving classes removed, points beyond
    the map builder's ``d_max`` dropped, a voxel grid of its ``voxel`` with the majority label
    (a raw scan's dense near rings would otherwise set the render's disc size)."""
    from semcal_ros.mapping.placement import placed_map

    static = scan.select(~np.isin(scan.label, np.array(list(MOVING_KITTI), np.uint16)))
    near = static.select(np.linalg.norm(static.xyz, axis=1) <= MAP_PARAMS.d_max)
    if len(near) == 0:
        raise InputError(f"none of the scan's {len(scan)} points is a static labelled point "
                         f"within {MAP_PARAMS.d_max:g} m of the lidar")
    return placed_map([static], [np.eye(4)], [stamp], MAP_PARAMS.d_max, MAP_PARAMS.voxel).map


class ScanBuffer:
    """The last ``size`` usable labelled scans (shared by every camera), thread safe; the
    reason the last unusable one was refused (cleared by the next good one)."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"parameter 'rig_scans_held' must be >= 1 scans, got {size}")
        self._scans: deque[Scan] = deque(maxlen=size)
        self._lock = threading.Lock()
        self.refusal = ""
        self.received = 0

    def add(self, scan: Scan) -> None:
        """Hold ``scan`` (one sent again, same stamp and frame, replaces the one held)."""
        with self._lock:
            again = [s for s in self._scans if (s.stamp, s.frame_id) == (scan.stamp,
                                                                            scan.frame_id)]
            for old in again:
                self._scans.remove(old)
            self._scans.append(scan)
            self.received += 1
            self.refusal = ""

    def refuse(self, reason: str) -> bool:
        """Keep ``reason``; True when it differs from the last one (log it once)."""
        with self._lock:
            self.received += 1
            new = reason != self.refusal
            self.refusal = reason
            return new

    def held(self) -> list[Scan]:
        """The scans held, oldest first."""
        with self._lock:
            return list(self._scans)

    def values(self) -> dict[str, Any]:
        with self._lock:
            out: dict[str, Any] = {"rig_scans_held": f"{len(self._scans)}/{self._scans.maxlen}"}
            if self.refusal:
                out["input_error.labelled_scan"] = self.refusal
            return out


class RigPairs:
    """One camera's last ``frames`` label image + scan pairs (see the module docstring).

    ``add_labels`` and ``resolve`` are called from the node's input callbacks (one callback
    group: one at a time); ``pairs`` from a goal (any thread)."""

    def __init__(self, frames: int, tolerance: float, scans: ScanBuffer,
                 waiting: int = 10) -> None:
        if frames < 1:
            raise ValueError(f"parameter 'rig_frames' must be >= 1 frames, got {frames}")
        if not tolerance > 0:
            raise ValueError(f"parameter 'rig_stamp_tolerance' must be > 0 s, got {tolerance}")
        self.frames, self.tolerance, self.scans = frames, tolerance, scans
        self._pairs: deque[Pair] = deque(maxlen=frames)
        self._waiting: deque[tuple[float, np.ndarray]] = deque()
        self._waiting_max = waiting
        self._lock = threading.Lock()
        self.unpaired = 0
        self.last_unpaired = ""
        self._unpaired_stamp: float | None = None

    def add_labels(self, stamp: float, labels: np.ndarray) -> None:
        """A usable label image: it waits for its scan (:meth:`resolve`). One sent again (same
        stamp) replaces the one waiting or paired."""
        with self._lock:
            self._waiting = deque(w for w in self._waiting if w[0] != stamp)
            self._waiting.append((stamp, labels))
            while len(self._waiting) > self._waiting_max:  # no scan comes: the oldest goes
                old, _ = self._waiting.popleft()
                self._count_unpaired(old, f"label image {old:.3f} s: {self._waiting_max} newer "
                                          "images waited for a scan")
        self.resolve()

    def resolve(self) -> None:
        """Pair every waiting label image whose nearest scan is settled (see the module
        docstring); count the ones that have none."""
        held = self.scans.held()
        if not held:
            return
        stamps = np.array([s.stamp for s in held])
        newest = float(stamps.max())
        with self._lock:
            still: deque[tuple[float, np.ndarray]] = deque()
            for stamp, labels in self._waiting:
                if newest < stamp:
                    still.append((stamp, labels))  # a nearer scan may still come
                    continue
                k = int(np.argmin(np.abs(stamps - stamp)))
                gap = abs(float(stamps[k]) - stamp)
                if gap <= self.tolerance:
                    kept = [p for p in self._pairs if p.labels_stamp != stamp]
                    self._pairs = deque(kept, maxlen=self.frames)
                    self._pairs.append(Pair(stamp, labels, held[k]))
                else:
                    self._count_unpaired(stamp, f"label image {stamp:.3f} s: the nearest held "
                                                f"scan is {gap:.3f} s away (rig_stamp_tolerance "
                                                f"{self.tolerance:g} s)")
            self._waiting = still

    def _count_unpaired(self, stamp: float, reason: str) -> None:
        if stamp != self._unpaired_stamp:  # an image sent again counts once
            self.unpaired += 1
        self._unpaired_stamp, self.last_unpaired = stamp, reason

    def pairs(self) -> list[Pair]:
        """The held pairs, oldest first."""
        with self._lock:
            return list(self._pairs)

    def values(self) -> dict[str, Any]:
        with self._lock:
            out: dict[str, Any] = {"rig_pairs": f"{len(self._pairs)}/{self.frames}",
                                   "rig_waiting": len(self._waiting),
                                   "rig_unpaired": self.unpaired}
            if self.last_unpaired:
                out["rig_last_unpaired"] = self.last_unpaired
        return {**out, **self.scans.values()}


class RigCameraInputs(CameraInputs):
    """:class:`CameraInputs` whose usable label images also go, with their stamps, to the
    camera's :class:`RigPairs`."""

    def __init__(self, *args: Any, rig: RigPairs, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.rig = rig

    def on_labels(self, msg: Any) -> bool:
        from semcal_ros.ros import conversions as conv

        if not super().on_labels(msg):
            return False
        labels = self.snapshot().labels
        if labels is not None:
            self.rig.add_labels(conv.stamp_to_seconds(msg.header.stamp), labels)
        return True

    def values(self) -> dict[str, Any]:
        return {**super().values(), **self.rig.values()}

    def problems(self, camera_frame_id: str = "") -> list[str]:
        """The camera's inputs and its pairs (see :func:`rig_problems`); empty: ready."""
        rig = self.rig
        return super().problems(camera_frame_id) + rig_problems(
            rig.pairs(), rig.frames, self.snapshot().camera, rig.unpaired,
            self._resolve(self._topic[LABELS]), self._resolve(SCANS_TOPIC))


def rig_goal_request(goal: Any, camera: RigCameraInputs, defaults: CalibrationParams,
                     default_seed: int) -> tuple[Request, list[Pair]]:
    """A runnable request over the camera's pairs, in the scans' (lidar) frame, and the pairs;
    or :class:`InputError` listing every problem of the goal."""
    pairs = camera.rig.pairs()
    problems = field_problems(goal, rig_frame_problems(pairs, goal.initial_pose.header.frame_id))
    problems += camera.problems(goal.camera_frame_id)
    if problems:
        raise InputError("; ".join(problems))
    bounds = validation.map_bounds(pairs[-1].scan.cloud.xyz)
    request = checked_request(goal, defaults, default_seed, pairs[-1].scan.frame_id, bounds,
                              camera.snapshot().camera)
    return request, pairs


def on_scan_message(msg: Any, scans: ScanBuffer, cameras: list[RigCameraInputs],
                    log_refusal: Callable[[str], None], topic: str) -> bool:
    """A labelled scan message: held and every camera's waiting images paired, or refused with
    one line (logged once per reason) while everything held stays. False when refused."""
    from semcal_ros.ros import conversions as conv

    try:
        scan = usable_scan(conv.pointcloud2_to_cloud(msg),
                           conv.stamp_to_seconds(msg.header.stamp), msg.header.frame_id)
    except ValueError as exc:  # InputError, or a layout the conversion cannot read
        text = f"{exc}; keeping the {len(scans.held())} scans and the pairs held"
        if scans.refuse(text):
            log_refusal(f"ignoring labelled scan on '{topic}': {text}")
        return False
    scans.add(scan)
    for camera in cameras:
        camera.rig.resolve()
    return True


def rig_problems(pairs: list[Pair], frames: int, camera: Any, unpaired: int,
                 labels_topic: str, scans_topic: str) -> list[str]:
    """What keeps a goal from calibrating over a camera's pairs (empty: it can run; the
    camera's own inputs are :meth:`CameraInputs.problems`'s)."""
    problems = []
    if len(pairs) < frames:
        problems.append(f"{len(pairs)} of rig_frames {frames} label image + labelled scan pairs "
                        f"held (labels on '{labels_topic}', scans on '{scans_topic}'; "
                        f"{unpaired} label images unpaired so far)")
    frame_ids = sorted({p.scan.frame_id for p in pairs})
    if len(frame_ids) > 1:
        problems.append(f"the held scans are in frames {', '.join(frame_ids)}: one rig, one "
                        "lidar frame")
    if camera is not None:
        sizes = sorted({f"{p.labels.shape[1]}x{p.labels.shape[0]}" for p in pairs
                        if p.labels.shape != (camera.height, camera.width)})
        if sizes:
            problems.append(f"held label images of {', '.join(sizes)} but CameraInfo says "
                            f"{camera.width}x{camera.height}")
    return problems


def rig_frame_problems(pairs: list[Pair], pose_frame: str) -> list[str]:
    """The goal's initial pose must be in the scans' (lidar) frame: the rig's extrinsic."""
    frame_ids = {p.scan.frame_id for p in pairs}
    if len(frame_ids) == 1 and pose_frame and pose_frame not in frame_ids:
        return [f"initial_pose is in frame '{pose_frame}' but the rig's scans are in "
                f"'{next(iter(frame_ids))}' (give the camera's pose in the lidar frame)"]
    return []


__all__ = ["SCANS_TOPIC", "Pair", "RigCameraInputs", "RigPairs", "Scan", "ScanBuffer",
           "frame_map", "on_scan_message", "rig_frame_problems", "rig_goal_request", "rig_problems",
           "usable_scan"]
