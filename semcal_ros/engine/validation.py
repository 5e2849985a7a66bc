"""What makes a calibration request runnable: one set of checks for ``semcal calibrate`` and the
``calibrate`` action.

Every check returns a list of problems (empty: fine), each one sentence naming the input or the
parameter and, for a limit, the limit itself, so a door can report all of them at once before any
work starts (a bad output folder found after a 5-minute calibration costs 5 minutes). Nothing here
imports rclpy: the command line runs without ROS, and the action turns its goal into the same
values before calling these.

Engine parameters are checked where they are defined (:mod:`semcal_ros.engine.params`: every value
finite, in range, the search bounds within the method's limits); here the same limits are applied
to the action's goal fields so that the message names the goal field. The limits (and why):

- ``MAX_BOUND_XYZ_M`` = 50 m per axis. The first Nelder-Mead simplex spans the whole bound and the
  map is cropped to ``render.crop_radius`` (120 m) around the initial pose; a view tens of metres
  off shows almost none of what the camera sees, so the loss is flat (the degenerate value) and
  the search wanders. The paper searches +-2.5 m.
- ``MAX_BOUND_DEG`` = 180 deg per angle: a larger bound wraps around and searches the same
  rotations twice (an unknown yaw is ``yaw_search``'s job, not a wide bound).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from semcal_ros.engine.params import MAX_BOUND_DEG, MAX_BOUND_XYZ_M, CalibrationParams
from semcal_ros.errors import InputError


def check(problems: Iterable[str], prefix: str = "") -> None:
    """:class:`~semcal_ros.errors.InputError` (a ValueError) listing every problem (one line),
    or nothing."""
    problems = list(problems)
    if problems:
        raise InputError(prefix + "; ".join(problems))


def _finite(values: Any) -> bool:
    try:
        return bool(np.all(np.isfinite(np.asarray(values, dtype=float))))
    except (TypeError, ValueError):
        return False


# --- poses and frames --------------------------------------------------------------------------
def pose_problems(translation: Sequence[float], quaternion: Sequence[float],
                  what: str = "initial_pose") -> list[str]:
    """Finite values and a unit quaternion (x, y, z, w)."""
    if not (_finite(translation) and _finite(quaternion)):
        return [f"{what} contains NaN or infinite values"]
    norm = float(np.linalg.norm(np.asarray(quaternion, dtype=float)))
    if abs(norm - 1.0) > 1e-3:
        return [f"{what} orientation is not a unit quaternion (norm {norm:.6g})"]
    return []


def frame_problems(pose_frame: str | None, map_frame: str, what: str = "initial_pose") -> list[str]:
    """The initial pose must be in the map's frame (nothing here can transform between frames:
    tf2 is not available)."""
    if pose_frame and pose_frame != map_frame:
        return [f"{what} is in frame '{pose_frame}' but the map is in '{map_frame}' "
                f"(give the pose in the map frame)"]
    return []


def bound_problems(translation_m: Sequence[float], rpy_deg: Sequence[float],
                   names: tuple[str, str] = ("bound_translation_m", "bound_rpy_deg")
                   ) -> list[str]:
    """The goal's per-axis search bounds: finite, not negative (0 = node default), within what
    the method can search (see the module docstring)."""
    problems = []
    for name, values, limit, unit in ((names[0], translation_m, MAX_BOUND_XYZ_M, "m"),
                                      (names[1], rpy_deg, MAX_BOUND_DEG, "deg")):
        for axis, value in zip("xyz", values):
            value = float(value)
            if not math.isfinite(value) or value < 0:
                problems.append(f"{name}.{axis} must be >= 0 (0 = node default), got {value}")
            elif value > limit:
                problems.append(f"{name}.{axis} {value:g} {unit} is beyond what the search can "
                                f"cover (at most {limit:g} {unit})")
    return problems


# --- camera, map, result -----------------------------------------------------------------------
def camera_problems(width: int, height: int, k: Any, d: Any) -> list[str]:
    """A camera the renderer can project with: a size, finite intrinsics, positive focal
    lengths (``k[0] <= 0`` alone lets NaN through)."""
    p = []
    if int(width) <= 0 or int(height) <= 0:
        p.append(f"image size {width}x{height} is empty")
    k = np.asarray(k, dtype=float).reshape(3, 3)
    if not _finite(k):
        p.append("K contains NaN or infinite values")
    elif not np.any(k):
        p.append("K is all zeros (camera not calibrated)")
    else:
        if not (k[0, 0] > 0 and k[1, 1] > 0):
            p.append(f"focal lengths must be positive, got fx {k[0, 0]:g}, fy {k[1, 1]:g}")
        if k[2, 2] != 1.0 or np.any(k[1, 0:1]) or np.any(k[2, :2]):
            p.append("K is not an upper-triangular pinhole matrix with K[2][2] = 1")
    if not _finite(d):
        p.append("distortion coefficients contain NaN or infinite values")
    return p


def map_bounds(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Bounding box of a (finite) map; None for an empty one."""
    if len(xyz) == 0:
        return None
    return np.min(xyz, axis=0), np.max(xyz, axis=0)


def reach_problems(position: Sequence[float], bounds: tuple[np.ndarray, np.ndarray] | None,
                   params: CalibrationParams, what: str = "initial_pose") -> list[str]:
    """The initial camera position close enough to the map that the engine sees some of it:
    within ``render.crop_radius`` (or ``render.far`` without a crop) of its bounding box."""
    if bounds is None:
        return ["the map has no point"]
    lo, hi = bounds
    pos = np.asarray(position, dtype=float)
    gap = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - pos, pos - hi))))
    reach = params.render.crop_radius or params.render.far
    if gap > reach:
        span = ", ".join(f"{a} {lo[i]:.1f}..{hi[i]:.1f}" for i, a in enumerate("xyz"))
        distance = f"{gap / 1000:.1f} km" if gap >= 1000 else f"{gap:.0f} m"
        return [f"{what} is {distance} from the map (map spans {span} m; the engine looks "
                f"{reach:g} m around the initial pose): check the pose and its frame"]
    return []


def result_problems(loss: float, params: CalibrationParams, coverage: float | None = None
                    ) -> list[str]:
    """A best result that must not be published: its view shows (almost) none of the map."""
    if not math.isfinite(loss) or loss >= params.loss.degenerate_loss:
        return [f"the best pose is degenerate (loss {loss:g} >= loss.degenerate_loss "
                f"{params.loss.degenerate_loss:g}: its view covers almost none of the label "
                f"image); nothing published; check the initial pose and the bounds"]
    if coverage is not None and coverage < params.loss.min_coverage:
        return [f"the best pose covers {coverage:.1%} of the label image (< loss.min_coverage "
                f"{params.loss.min_coverage:g}); nothing published"]
    return []


# --- files -------------------------------------------------------------------------------------
def output_problems(path: str | Path | None, what: str) -> list[str]:
    """An output file that can be written once the work is done: not a folder, and its folder
    exists as a writable folder or can be created inside one."""
    if path is None or str(path) == "":
        return []
    path = Path(path).expanduser()
    if path.is_dir():
        return [f"{what} {path} is a folder, not a file"]
    parent = path.parent if str(path.parent) else Path(".")
    existing = parent
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if not existing.is_dir():
        return [f"{what} {path}: {existing} is not a folder"]
    if not os.access(existing, os.W_OK | os.X_OK):
        return [f"{what} {path}: folder {existing} is not writable"]
    if path.exists() and not os.access(path, os.W_OK):
        return [f"{what} {path} exists and is not writable"]
    return []
