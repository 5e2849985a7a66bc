"""What the ``calibrator`` says: the action result's text and quality fields, and its /diagnostics.

Kept apart from the node so the node is wiring and every text a caller or an operator reads is
in one place (docs/ros.md lists them): the success message (ending "verdict <v>"), the result's
quality fields, the goal state ("idle", "queued <id>", "running <id> (<stage>, <n>
evaluations)"), and the node's and each camera's status — inputs, goal, and the verdict of the
last result (WARN inconclusive, ERROR failed). A failed goal keeps the verdict of the transform
that stays published.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from geometry_msgs.msg import Vector3

from semcal_ros.engine.results import CalibrationResult, QualityReport
from semcal_ros.ros.diagnostics import Level, Report
from semcal_ros.ros.engine_job import GoalRunner
from semcal_ros.ros.map_intake import MapIntake


def success_message(result: CalibrationResult, camera_frame: str) -> str:
    """The action result's message of a calibration that succeeded."""
    rpy = result.pose.body_rpy_deg()
    q = result.quality
    return (f"calibrated '{camera_frame}': t = "
            f"[{', '.join(f'{v:.3f}' for v in result.pose.translation)}] m, rpy = "
            f"[{', '.join(f'{v:.2f}' for v in rpy)}] deg, loss {result.loss:.5f}, "
            f"{result.accepted}/{len(result.runs)} runs agree within "
            f"{result.spread_translation_m * 100:.1f} cm / "
            f"{result.spread_rotation_deg:.3f} deg, {result.seconds:.1f} s"
            + (f", verdict {q.verdict}" if q is not None else ""))


def result_fields(result: CalibrationResult) -> dict[str, Any]:
    """The Calibrate result's figures (besides message and transform) of a success."""
    return {"loss": float(result.loss),
            "spread_translation_m": float(result.spread_translation_m),
            "spread_rotation_deg": float(result.spread_rotation_deg),
            "evaluations": int(result.evaluations), "seconds": float(result.seconds),
            **quality_fields(result.quality)}


def quality_fields(q: QualityReport | None) -> dict[str, Any]:
    """The Calibrate result's quality fields from a QualityReport (none: left empty)."""
    if q is None:
        return {}
    return {"verdict": q.verdict, "verdict_reason": q.reason, "agreement": float(q.agreement),
            "agreement_classes": list(q.agreement_per_class),
            "agreement_per_class": [float(v) for v in q.agreement_per_class.values()],
            "coverage": float(q.coverage),
            "uncertainty_translation_m": Vector3(
                **dict(zip("xyz", map(float, q.uncertainty_translation_m)))),
            "uncertainty_rpy_deg": Vector3(**dict(zip("xyz", map(float, q.uncertainty_rpy_deg))))}


def quality_values(q: QualityReport | None) -> dict[str, Any]:
    """The verdict and its figures as /diagnostics key/values."""
    if q is None:
        return {"verdict": "none"}
    ut, ur = q.uncertainty_translation_m, q.uncertainty_rpy_deg
    return {"verdict": q.verdict, "verdict_reason": q.reason,
            "agreement": round(float(q.agreement), 4), "coverage": round(float(q.coverage), 4),
            "uncertainty_cm": "/".join(f"{v * 100:.1f}" for v in ut),
            "uncertainty_deg": "/".join(f"{v:.3f}" for v in ur)}


@dataclass
class LastResult:
    message: str
    quality: QualityReport | None = None  # of the last success (the transform published)


class CalibratorStatus:
    """The calibrator's status: the answers it gave (:meth:`record`) and the reports the
    diagnostics publish (:meth:`report`, :meth:`camera_reports`).

    ``cameras``: name -> CameraInputs; ``missing(camera)``: what the single camera still lacks
    for a goal; ``map_topic``: the resolved map topic; ``needs_map`` False: no map is missing
    (a rig's goals calibrate against its scans)."""

    def __init__(self, cameras: Mapping[str, Any], goals: GoalRunner, maps: MapIntake,
                 missing: Callable[[Any], list[str]], map_topic: str,
                 needs_map: bool = True) -> None:
        self.cameras, self.goals, self.maps = cameras, goals, maps
        self.missing, self.map_topic = missing, map_topic
        self.needs_map = needs_map  # False: a rig calibrates against its scans, not the map
        self._lock = threading.Lock()
        self._last: dict[str, LastResult] = {}
        self.last_result = ""  # the latest answer of any camera

    @property
    def named(self) -> bool:
        return "" not in self.cameras

    def record(self, camera: str | None, succeeded: bool, message: str,
               quality: QualityReport | None = None) -> None:
        """A goal was answered (``camera`` None: before it was known, e.g. an invalid goal)."""
        with self._lock:
            if camera is not None or len(self.cameras) == 1:
                key = camera if camera is not None else next(iter(self.cameras))
                previous = self._last.get(key)
                # a failure keeps the verdict of the transform that stays published
                kept = quality if succeeded else (previous.quality if previous else None)
                self._last[key] = LastResult(message, kept)
            self.last_result = message

    def state(self, name: str) -> str:
        s = self.goals.state(name)
        if s is None:
            return "idle"
        if s.stage == "queued":
            return f"queued {s.goal_id}"
        return f"running {s.goal_id} ({s.stage}, {s.evaluations} evaluations)"

    def map_values(self) -> dict[str, Any]:
        held = self.maps.held
        values: dict[str, Any] = {
            "map_points": held.points if held is not None else 0,
            "map_points_prepared": len(held.prepared.xyz) if held is not None else 0,
            "map_frame": self.maps.frame,
            "map_source": held.source if held is not None else "none",
        }
        if self.maps.refusal:
            values["input_error.map"] = self.maps.refusal
        return values

    def camera_report(self, camera: Any, missing: list[str]) -> Report:
        """Level, message and values of one camera (or of the node with its single camera)."""
        values = camera.values()
        with self._lock:
            last = self._last.get(camera.name)
        values["state"] = self.state(camera.name)
        values["last_result"] = last.message if last else "none"
        values.update(quality_values(last.quality if last else None))
        refusals = camera.refusals()
        if refusals:
            return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in refusals.items()), values
        if missing:
            return Level.WARN, "; ".join(missing), values
        running = values["state"] != "idle"
        q = last.quality if last else None
        if q is not None and q.verdict != "good" and not running:
            level = Level.ERROR if q.verdict == "failed" else Level.WARN
            return level, f"last calibration {q.verdict}: {q.reason}", values
        return Level.OK, "calibrating" if running else "ready", values

    def report(self) -> Report:
        """The node's status; with the single unnamed camera it is that camera's too."""
        values = self.map_values()
        values["last_rejection"] = self.goals.last_rejection or "none"
        map_error = values.get("input_error.map")
        if not self.named:
            camera = self.cameras[""]
            level, message, cam_values = self.camera_report(camera, self.missing(camera))
            values = {**values, **cam_values}
            if map_error:
                errors = {"map": map_error, **camera.refusals()}
                return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in errors.items()), values
            return level, message, values
        states = {name: self.state(name) for name in self.cameras}
        busy = {n: s for n, s in states.items() if s != "idle"}
        values["state"] = "; ".join(f"{n}: {s}" for n, s in busy.items()) or "idle"
        values["cameras"] = ", ".join(self.cameras)
        values["last_result"] = self.last_result or "none"
        if map_error:
            return Level.ERROR, f"map: {map_error}", values
        if values["map_source"] == "none" and self.needs_map:
            return Level.WARN, f"no map received yet (topic '{self.map_topic}')", values
        return Level.OK, "calibrating" if busy else "ready", values

    def camera_reports(self) -> dict[str, Report]:
        return {name: self.camera_report(camera, camera.problems())
                for name, camera in self.cameras.items()}


__all__ = ["CalibratorStatus", "LastResult", "quality_fields", "quality_values",
           "result_fields", "success_message"]
