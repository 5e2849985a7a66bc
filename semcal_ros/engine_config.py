"""CalibrationParams from a ROS 2 parameter file: the one reader for the CLI and the tests."""

from __future__ import annotations

from pathlib import Path

from semcal_ros.config import apply_flat, load_node_params
from semcal_ros.params import CalibrationParams

ENGINE_GROUPS = ("render", "loss", "search", "schedule", "verification")


def load_calibration_params(path: str | Path | None, node: str = "calibrator",
                            base: CalibrationParams | None = None) -> CalibrationParams:
    """Engine parameters from ``path`` (node-only parameters in the same file are skipped);
    an unknown name inside an engine group is an error, so typos do not pass silently."""
    params = base or CalibrationParams()
    if path is None:
        return params
    flat = load_node_params(path, node)
    engine = {k: v for k, v in flat.items() if k.split(".", 1)[0] in ENGINE_GROUPS}
    try:
        return apply_flat(params, engine, strict=True)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
