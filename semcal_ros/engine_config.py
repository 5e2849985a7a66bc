"""Kept only until every caller uses :meth:`CalibrationParams.from_file` (same behaviour)."""

from __future__ import annotations

from pathlib import Path

from semcal_ros.params import CalibrationParams


def load_calibration_params(path: str | Path | None, node: str = "calibrator",
                            base: CalibrationParams | None = None) -> CalibrationParams:
    return CalibrationParams.from_file(path, node, base)
