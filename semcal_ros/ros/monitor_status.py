"""What the ``calibration_monitor`` says: its ``calibration/drift`` message and its /diagnostics.

Kept apart from the node so that the node is wiring and the texts and levels are read in one
place (docs/drift.md lists them). The decisions behind them — the reference, the confirmation,
the level shown — are :class:`~semcal_ros.engine.drift_watch.DriftWatch`'s.
"""

from __future__ import annotations

from typing import Any

from semcal_interfaces.msg import CalibrationDrift
from semcal_ros.engine.drift_watch import DriftWatch, Verdict
from semcal_ros.ros import conversions as conv
from semcal_ros.ros.diagnostics import Level, Report

#: diagnostics level per drift level; "cannot judge" is a WARN (CalibrationDrift has no level
#: for it either)
LEVEL = {"ok": Level.OK, "warn": Level.WARN, "error": Level.ERROR, "unknown": Level.WARN}


def drift_message(verdict: Verdict, camera_frame_id: str, header: Any) -> CalibrationDrift:
    """The latched ``calibration/drift`` message of one check."""
    report = verdict.report
    msg = CalibrationDrift(camera_frame_id=camera_frame_id, level=int(LEVEL[verdict.shown]))
    msg.header = header
    msg.message = verdict.message
    msg.drift_translation_m = float(report.drift_translation_m)
    msg.drift_rotation_deg = float(report.drift_rotation_deg)
    msg.drift_xyz_m.x, msg.drift_xyz_m.y, msg.drift_xyz_m.z = report.drift_xyz_m
    msg.loss_calibrated = float(report.loss_calibrated)
    msg.loss_best = float(report.loss_best)
    if report.calibrated is not None:
        msg.calibrated_pose = conv.pose_to_msg(report.calibrated)
    if report.estimated is not None:
        msg.estimated_pose = conv.pose_to_msg(report.estimated)
    msg.seconds = float(report.seconds)
    return msg


def camera_report(watch: DriftWatch, calibration_source: str, inputs: Any) -> Report:
    """One camera's status: its inputs, the last check and the level shown. (Call under the
    node's lock: it reads the watch.)"""
    last, shown = watch.last, watch.shown
    values: dict[str, Any] = {"calibration_source": calibration_source, "checks": watch.checks,
                              "reference": "yes" if watch.reference else "no",
                              # label images the checks fuse (label_window), as the calibrator's
                              "label_window": f"{len(watch.recent)}/{watch.window}"}
    values.update(inputs.values())
    refusals = inputs.refusals()
    if last is None:
        return Level.WARN, "no check yet", values
    values.update({"drift_cm": round(last.drift_translation_m * 100, 2),
                   "drift_deg": round(last.drift_rotation_deg, 4),
                   "drift_xyz_cm": "/".join(f"{v * 100:.1f}" for v in last.drift_xyz_m),
                   "loss_calibrated": last.loss_calibrated, "loss_best": last.loss_best,
                   "check_seconds": round(last.seconds, 3), "last_level": last.level})
    if refusals:
        return Level.ERROR, "; ".join(f"{k}: {v}" for k, v in refusals.items()), values
    if shown == "unknown":
        return Level.WARN, f"cannot judge: {last.message}", values
    return LEVEL[shown], f"{shown.upper()}: {last.message}" if shown != "ok" else \
        last.message, values


def node_report(values: dict[str, Any], parts: dict[str, Report]) -> Report:
    """The node's status: the single unnamed camera's (``parts`` keyed ""), or the worst of the
    named cameras'."""
    if "" in parts:
        level, message, cam_values = parts[""]
        return level, message, {**values, **cam_values}
    worst = max((p[0] for p in parts.values()), default=Level.OK)
    flagged = [n for n, p in parts.items() if p[0] == worst and worst != Level.OK]
    return worst, (f"{len(parts)} cameras" + (f"; {', '.join(flagged)}: {worst.name}"
                                              if flagged else ": OK")), values


__all__ = ["LEVEL", "camera_report", "drift_message", "node_report"]
