"""A node's map intake: the map file at start, then the latched ``map`` topic, refusals kept apart.

The calibrator and the calibration monitor take their map the same way, so they share this: a
message is converted (labels required), its NaN points dropped with a warning, and the rest
prepared once (:class:`~semcal_ros.ros.held_map.HeldMap`). A message that cannot be used is
refused with one line — the reason and "keeping the map held (...)" — logged once per distinct
reason and kept as :attr:`MapIntake.refusal` for the diagnostics; the map held before stays.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.errors import InputError
from semcal_ros.ros import conversions as conv
from semcal_ros.ros.held_map import HeldMap


def usable_map(msg: Any, warn: Callable[[str], None]) -> LabelledCloud:
    """The finite points of a map message; :class:`InputError` when none is left (``warn`` is
    told how many NaN points were dropped)."""
    raw = conv.pointcloud2_to_cloud(msg, require_label=True)
    cloud = raw.finite()
    if len(cloud) == 0:
        raise InputError("the map message is empty" if len(raw) == 0 else
                         f"the map message has no finite point ({len(raw)} points, all NaN or "
                         "infinite)")
    if len(cloud) < len(raw):
        warn(f"map: {len(raw) - len(cloud)} of {len(raw)} points are NaN or infinite and were "
             "dropped")
    return cloud


class MapIntake:
    """The map a node holds (None before the first), thread-safe. ``on_new(held)`` is called
    after a new map replaced the old one (e.g. the drift watch takes new references)."""

    def __init__(self, mapping: LabelMapping, default_frame: str, logger: Any,
                 on_new: Callable[[HeldMap], None] | None = None) -> None:
        self.mapping, self.default_frame, self.logger = mapping, default_frame, logger
        self.on_new = on_new
        self._lock = threading.Lock()
        self._held: HeldMap | None = None
        self.refusal = ""  # why the latest map message was refused ("" once one is taken)

    @property
    def held(self) -> HeldMap | None:
        with self._lock:
            return self._held

    @property
    def frame(self) -> str:
        """The map frame: the held map's, else the node's ``map_frame``."""
        held = self.held
        return held.frame if held is not None else self.default_frame

    def describe(self) -> str:
        held = self.held
        return f"{held.points} points" if held is not None else "none"

    def load_file(self, path: str) -> HeldMap:
        """The map file given at start (an unusable one stops the node: ValueError)."""
        from semcal_ros.io.ply import read_ply

        held = HeldMap.from_cloud(read_ply(path).finite(), self.mapping, self.default_frame, path)
        self._take(held)
        self.logger.info(f"map from {path}: {held.points} points (prepared in "
                         f"{held.seconds:.1f} s)")
        return held

    def on_message(self, msg: Any) -> None:
        """A map message: taken, or refused with the reason while the held map stays."""
        try:
            cloud = usable_map(msg, self.logger.warning)
            held = HeldMap.from_cloud(cloud, self.mapping,
                                      msg.header.frame_id or self.default_frame, "topic")
        except ValueError as exc:  # InputError, or a layout conversions cannot read
            text = f"{exc}; keeping the map held ({self.describe()})"
            if text != self.refusal:
                self.logger.error(f"ignoring map: {text}")
            self.refusal = text
            return
        del cloud  # only the prepared map stays
        first = self._take(held)
        if first:
            self.logger.info(f"map received: {held.points} points in '{held.frame}' "
                             f"(prepared in {held.seconds:.1f} s)")

    def _take(self, held: HeldMap) -> bool:
        """Hold ``held``; True when it is the first map from the topic."""
        with self._lock:
            first = self._held is None or self._held.source != "topic"
            self._held, self.refusal = held, ""
        if self.on_new is not None:
            self.on_new(held)
        return first


__all__ = ["MapIntake", "usable_map"]
