"""A calibrated pose in the forms other ROS tools read: URDF, a static_transform_publisher line,
4x4 matrices.

Users otherwise convert the quaternion by hand and get the Euler order or the direction of the
transform wrong. Each form here states its convention and is tested by parsing it back with that
tool's public convention (URDF: fixed-axis roll, pitch, yaw = scipy ``'xyz'`` extrinsic;
static_transform_publisher: the pose of the child frame in the parent; matrices: ``T_a_b`` maps
points of frame b into frame a) and composing it to the pose within 1e-9.

Numbers are written with ``repr`` of Python floats (the shortest text that reads back to the same
double), so nothing is lost on the way. No rclpy here: the CLI (``semcal export-pose``) is a thin
adapter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from semcal_ros.io.files import load_yaml
from semcal_ros.engine.pose import BODY_FROM_OPTICAL, Pose

#: The output forms of ``semcal export-pose --format``.
FORMATS = ("urdf", "static-tf", "matrix")

#: The fixed joint from a REP-103 body frame (x forward, y left, z up) to the optical frame
#: (z forward, x right, y down): camera drivers' xacro files write it ``-pi/2 0 -pi/2``, but that
#: is xacro's expression syntax; URDF readers (urdfdom, urdf_parser_py) take plain numbers only.
BODY_TO_OPTICAL_RPY = f"{-math.pi / 2!r} 0 {-math.pi / 2!r}"

MATRIX_CONVENTION = ("T_<a>_<b> is the 4x4 homogeneous transform that maps points given in frame "
                     "<b> into frame <a> (p_a = T_a_b @ [x, y, z, 1]); its last column is the "
                     "origin of <b> in <a>, its rotation columns the axes of <b> in <a>; metres")


@dataclass(frozen=True)
class FramedPose:
    """A pose YAML of docs/CONTRACTS.md: the child frame's pose in the parent frame."""

    parent: str
    child: str
    pose: Pose


def _frame_name(data: dict, key: str, path: str) -> str:
    value = data.get(key)
    if value is None:
        raise ValueError(f"{path}: missing field '{key}'")
    if not isinstance(value, str) or not value.strip() or any(c.isspace() for c in value):
        raise ValueError(f"{path}: '{key}' must be a frame name without spaces, got {value!r}")
    return value


def _numbers(data: dict, key: str, length: int, path: str) -> np.ndarray:
    value = data.get(key)
    if value is None:
        raise ValueError(f"{path}: missing field '{key}'")
    if (not isinstance(value, (list, tuple)) or len(value) != length
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise ValueError(f"{path}: '{key}' must be a list of {length} numbers, got {value!r}")
    out = np.array(value, dtype=float)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{path}: '{key}' contains NaN or infinite values")
    return out


def framed_pose_from_dict(data: Any, path: str = "pose") -> FramedPose:
    """Check a pose mapping field by field (ValueError naming the file and the field)."""
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping (a pose file of docs/CONTRACTS.md)")
    parent, child = _frame_name(data, "frame_id", path), _frame_name(data, "child_frame_id", path)
    if parent == child:
        raise ValueError(f"{path}: frame_id and child_frame_id are both '{parent}'")
    translation = _numbers(data, "translation", 3, path)
    if "rotation" in data or "rpy_deg" not in data:
        q = _numbers(data, "rotation", 4, path)
        norm = float(np.linalg.norm(q))
        if norm == 0.0:
            raise ValueError(f"{path}: 'rotation' is a zero quaternion")
        try:
            pose = Pose(translation, q)
        except ValueError as exc:
            raise ValueError(f"{path}: 'rotation': {exc}") from None
    else:
        pose = Pose.from_body_rpy_deg(translation, _numbers(data, "rpy_deg", 3, path))
    return FramedPose(parent, child, pose)


def read_framed_pose(path: str | Path) -> FramedPose:
    """A pose YAML file; FileNotFoundError / ValueError in one line."""
    return framed_pose_from_dict(load_yaml(path, "pose"), str(path))


# --- the forms ---------------------------------------------------------------------------------
def _num(value: float) -> str:
    """Full precision: repr of the double (reads back bit for bit); no '-0.0'."""
    value = float(value)
    return repr(0.0 if value == 0.0 else value)


def urdf_rpy(rotation: np.ndarray) -> np.ndarray:
    """URDF's fixed-axis roll, pitch, yaw (R = Rz(yaw) Ry(pitch) Rx(roll)) of a rotation matrix."""
    return Rotation.from_matrix(rotation).as_euler("xyz")


def _joint(name: str, parent: str, child: str, xyz: str, rpy: str) -> str:
    return (f"  <joint name={quoteattr(name)} type=\"fixed\">\n"
            f"    <parent link={quoteattr(parent)}/>\n"
            f"    <child link={quoteattr(child)}/>\n"
            f"    <origin xyz=\"{xyz}\" rpy=\"{rpy}\"/>\n"
            f"  </joint>\n")


def to_urdf(fp: FramedPose, body_frame: str | None = None) -> str:
    """A ``<robot name="semcal_calibration">``: a link per frame, fixed joints parent -> child.

    The joint's origin is the child's pose in the parent (URDF convention). With ``body_frame``
    the calibrated joint goes to that REP-103 body frame (x forward, y left, z up) and a second
    fixed joint (rpy -pi/2 0 -pi/2, written as plain numbers: :data:`BODY_TO_OPTICAL_RPY`)
    leads to the optical child frame. Every attribute is a plain number a URDF parser reads.
    """
    if body_frame is not None and body_frame in (fp.parent, fp.child):
        raise ValueError(f"--body-frame '{body_frame}' must differ from the pose's frames "
                         f"('{fp.parent}', '{fp.child}')")
    if body_frame is not None and (not body_frame.strip() or any(c.isspace() for c in body_frame)):
        raise ValueError(f"--body-frame must be a frame name without spaces, got {body_frame!r}")
    rotation = fp.pose.rotation
    target = fp.child if body_frame is None else body_frame
    if body_frame is not None:
        rotation = rotation @ BODY_FROM_OPTICAL.T  # the body frame's axes in the parent
    xyz = " ".join(_num(v) for v in fp.pose.translation)
    rpy = " ".join(_num(v) for v in urdf_rpy(rotation))
    links = [fp.parent, target] + ([fp.child] if body_frame is not None else [])
    text = ("<?xml version=\"1.0\"?>\n"
            "<!-- written by semcal export-pose: the calibrated pose of "
            f"{fp.child} in {fp.parent}; origin = child pose in parent, rpy = fixed-axis "
            "roll, pitch, yaw (rad) -->\n"
            "<robot name=\"semcal_calibration\">\n")
    text += "".join(f"  <link name={quoteattr(link)}/>\n" for link in links)
    text += _joint(f"{fp.parent}_to_{target}", fp.parent, target, xyz, rpy)
    if body_frame is not None:
        text += _joint(f"{body_frame}_to_{fp.child}", body_frame, fp.child, "0 0 0",
                       BODY_TO_OPTICAL_RPY)
    return text + "</robot>\n"


def to_static_tf(fp: FramedPose) -> str:
    """One ``ros2 run tf2_ros static_transform_publisher`` line with the new-style flags."""
    t, q = fp.pose.translation, fp.pose.quaternion
    values = dict(zip(("x", "y", "z"), t)) | dict(zip(("qx", "qy", "qz", "qw"), q))
    flags = " ".join(f"--{k} {_num(v)}" for k, v in values.items())
    return (f"ros2 run tf2_ros static_transform_publisher {flags} "
            f"--frame-id {fp.parent} --child-frame-id {fp.child}\n")


def homogeneous(pose: Pose) -> np.ndarray:
    """T_parent_child: maps child-frame points into the parent frame."""
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = pose.rotation, pose.translation
    return out


def inverse(t: np.ndarray) -> np.ndarray:
    """The exact rigid inverse (R^T, -R^T t), not a general matrix inverse."""
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def to_matrix(fp: FramedPose) -> str:
    """YAML with ``T_<parent>_<child>``, ``T_<child>_<parent>`` (nested lists) and a
    ``convention:`` line."""
    forward = homogeneous(fp.pose)

    def rows(m: np.ndarray) -> list[list[float]]:  # YAML writes floats with repr; no -0.0
        return [[float(v) + 0.0 for v in row] for row in m]

    data = {"convention": MATRIX_CONVENTION,
            f"T_{fp.parent}_{fp.child}": rows(forward),
            f"T_{fp.child}_{fp.parent}": rows(inverse(forward))}
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=10_000)


def export_pose(fp: FramedPose, fmt: str, body_frame: str | None = None) -> str:
    """The text of one form (``FORMATS``)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown format '{fmt}' (choose from {', '.join(FORMATS)})")
    if body_frame is not None and fmt != "urdf":
        raise ValueError("--body-frame applies to --format urdf only")
    if fmt == "urdf":
        return to_urdf(fp, body_frame)
    if fmt == "static-tf":
        return to_static_tf(fp)
    return to_matrix(fp)


__all__ = ["BODY_TO_OPTICAL_RPY", "FORMATS", "FramedPose", "MATRIX_CONVENTION", "export_pose",
           "framed_pose_from_dict", "homogeneous", "inverse", "read_framed_pose", "to_matrix",
           "to_static_tf", "to_urdf", "urdf_rpy"]
