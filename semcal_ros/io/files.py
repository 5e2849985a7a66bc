"""YAML and image files of the engine: poses, camera_info, label images."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import finite_rows
from semcal_ros.engine.pose import Pose
from semcal_ros.readers import imread, load_yaml


#: A scan or map file with fewer distinct finite points than this is refused: it cannot be a
#: scan (a file of 5000 copies of one point was once labelled "road 100 %" without a word).
MIN_DISTINCT_POINTS = 10


def _distinct(points: np.ndarray, minimum: int) -> int:
    """How many distinct rows ``points`` has, counted up to ``minimum``: one pass per distinct
    row found (the next row unlike every one found so far)."""
    remaining = np.ones(len(points), bool)
    distinct = 0
    while distinct < minimum and remaining.any():
        point = points[int(np.argmax(remaining))]
        remaining &= np.any(points != point, axis=1)
        distinct += 1
    return distinct


def distinct_points_problem(xyz: np.ndarray, minimum: int = MIN_DISTINCT_POINTS) -> str:
    """Why the cloud ``xyz`` (N, 3) is no scan ("" when it has ``minimum`` distinct finite
    points or no finite point at all: an empty or all-NaN cloud is its reader's caller's to
    refuse, in its own words). Cheap on millions of points: the first few thousand rows
    usually settle it (a scan's first ``minimum`` distinct points, in ``minimum`` passes over
    them: 0.1 ms where sorting them took 1-2 ms, on every scan the map builder reads), else at
    most ``minimum`` passes over the cloud."""
    xyz = np.asarray(xyz)
    head = xyz[:4096]
    if _distinct(head[finite_rows(head)], minimum) >= minimum:
        return ""
    finite = xyz[finite_rows(xyz)]
    if len(finite) == 0:
        return ""
    distinct = _distinct(finite, minimum)
    if distinct >= minimum:
        return ""
    return (f"only {distinct} distinct point{'s' * (distinct > 1)} among {len(finite)} "
            f"(fewer than {minimum}): not a scan")


def read_camera_info(path: str | Path) -> CameraModel:
    data = load_yaml(path, "camera_info")
    try:
        return CameraModel.from_camera_info_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def write_camera_info(path: str | Path, camera: CameraModel, name: str = "camera") -> None:
    Path(path).write_text(yaml.safe_dump(camera.to_camera_info_dict(name), sort_keys=False))


def pose_from_dict(data: dict) -> Pose:
    """A pose YAML mapping: translation + rotation quaternion, or translation + rpy_deg (body)."""
    if "translation" not in data:
        raise ValueError("pose has no 'translation'")
    t = np.asarray(data["translation"], dtype=float)
    if t.shape != (3,):
        raise ValueError("pose 'translation' must be [x, y, z]")
    if "rotation" in data:
        q = np.asarray(data["rotation"], dtype=float)
        if q.shape != (4,):
            raise ValueError("pose 'rotation' must be a quaternion [qx, qy, qz, qw]")
        return Pose(t, q)
    if "rpy_deg" in data:
        rpy = np.asarray(data["rpy_deg"], dtype=float)
        if rpy.shape != (3,) or not np.all(np.isfinite(rpy)):
            raise ValueError("pose 'rpy_deg' must be [roll, pitch, yaw] in degrees")
        return Pose.from_body_rpy_deg(t, rpy)
    raise ValueError("pose has neither 'rotation' nor 'rpy_deg'")


def read_pose(path: str | Path) -> Pose:
    data = load_yaml(path, "pose")
    try:
        return pose_from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def pose_to_dict(pose: Pose, extra: dict[str, Any] | None = None,
                 frame_id: str = "map", child_frame_id: str = "camera_optical") -> dict:
    out: dict[str, Any] = {
        "frame_id": frame_id,
        "child_frame_id": child_frame_id,
        "translation": [float(v) for v in pose.translation],
        "rotation": [float(v) for v in pose.quaternion],
    }
    out.update(extra or {})
    return out


def write_pose(path: str | Path, pose: Pose, extra: dict[str, Any] | None = None) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(pose_to_dict(pose, extra), sort_keys=False))


def read_label_image(path: str | Path) -> np.ndarray:
    """8-bit single-channel Cityscapes trainId image."""
    img = imread(path, cv2.IMREAD_UNCHANGED, "label image")
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"{path}: label image must be 8-bit single channel "
                         f"(got {img.dtype}, {img.ndim} dims)")
    return img


def write_label_image(path: str | Path, labels: np.ndarray) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(labels, dtype=np.uint8)):
        raise OSError(f"could not write {path}")


def write_rgb_image(path: str | Path, rgb: np.ndarray) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")


def read_rgb_image(path: str | Path) -> np.ndarray:
    return cv2.cvtColor(imread(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
