"""The scans of a scene folder: ``scans/NNNNNN.ply`` and ``scans/poses.yaml`` (docs/CONTRACTS.md).

``poses.yaml`` gives one pose per scan file. Poses are of the lidar in the map frame unless
``child_frame_id`` names another frame (a vehicle frame), in which case ``lidar_extrinsic`` (the
lidar in that frame) must be present; :func:`read_scan_poses` then returns lidar poses, so callers
never have to know which of the two the file held.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io.files import load_yaml
from semcal_ros.io.files import pose_from_dict
from semcal_ros.io.ply import read_ply

LIDAR_FRAMES = ("lidar", "velodyne", "lidar_link")


def matrix_from_dict(data: dict, where: str) -> np.ndarray:
    """4x4 from ``{translation: [x, y, z], rotation: [qx, qy, qz, qw]}`` (checked as a Pose)."""
    if not isinstance(data, dict) or "rotation" not in data:
        raise ValueError(f"{where}: needs 'translation' and 'rotation' [qx, qy, qz, qw]")
    try:
        pose = pose_from_dict(data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None
    out = np.eye(4)
    out[:3, :3] = pose.rotation
    out[:3, 3] = pose.translation
    return out


def matrix_to_dict(matrix: np.ndarray) -> dict[str, list[float]]:
    return {"translation": [float(v) for v in matrix[:3, 3]],
            "rotation": [float(v) for v in Rotation.from_matrix(matrix[:3, :3]).as_quat()]}


@dataclass(frozen=True)
class ScanPoses:
    """Scan files with their lidar poses (4x4, lidar in map) and stamps, in file order."""

    folder: Path
    files: list[Path]
    stamps: np.ndarray  # (N,) seconds
    poses: np.ndarray  # (N, 4, 4) lidar in the map frame
    frame_id: str

    def __len__(self) -> int:
        return len(self.files)

    def scan(self, i: int) -> LabelledCloud:
        return read_scan(self.files[i])


def read_scan(path: str | Path) -> LabelledCloud:
    """One scan PLY (x, y, z, optional intensity and label); the label is optional for scans."""
    return read_ply(path, require_label=False)


def read_scan_poses(path: str | Path) -> ScanPoses:
    """Parse ``poses.yaml`` (or ``poses_true.yaml``); scans are listed relative to its folder."""
    path = Path(path)
    data = load_yaml(path, "scan poses")
    if not isinstance(data.get("scans"), list):
        raise ValueError(f"{path}: expected a 'scans' list")
    child = str(data.get("child_frame_id", "lidar"))
    extrinsic = np.eye(4)
    if child not in LIDAR_FRAMES:
        if "lidar_extrinsic" not in data:
            raise ValueError(f"{path}: poses are of '{child}', not the lidar, but no "
                             "'lidar_extrinsic' (the lidar in that frame) is given")
        extrinsic = matrix_from_dict(data["lidar_extrinsic"], f"{path}: lidar_extrinsic")
    files, stamps, poses = [], [], []
    for i, entry in enumerate(data["scans"]):
        where = f"{path}: scans[{i}]"
        if not isinstance(entry, dict) or "file" not in entry:
            raise ValueError(f"{where}: expected a mapping with 'file'")
        if "stamp" not in entry:
            raise ValueError(f"{where}: no 'stamp'")
        files.append(path.parent / str(entry["file"]))
        stamps.append(float(entry["stamp"]))
        poses.append(matrix_from_dict(entry, where) @ extrinsic)
    if not files:
        raise ValueError(f"{path}: the 'scans' list is empty")
    return ScanPoses(path.parent, files, np.array(stamps), np.array(poses),
                     str(data.get("frame_id", "map")))


def write_scan_poses(path: str | Path, files: list[str], stamps: np.ndarray, poses: np.ndarray,
                     frame_id: str = "map", extra: dict[str, Any] | None = None) -> None:
    """Write lidar poses in the ``poses.yaml`` format (e.g. the poses after ICP refinement)."""
    scans = [{"file": str(f), "stamp": float(s), **matrix_to_dict(p)}
             for f, s, p in zip(files, stamps, poses)]
    data: dict[str, Any] = {"frame_id": frame_id, "child_frame_id": "lidar", **(extra or {}),
                            "scans": scans}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


def is_scene_folder(root: str | Path) -> bool:
    return (Path(root) / "scans" / "poses.yaml").is_file()


def open_scene_scans(root: str | Path, true_poses: bool = False) -> ScanPoses:
    """The scans of scene folder ``root`` (``poses_true.yaml`` with ``true_poses``)."""
    name = "poses_true.yaml" if true_poses else "poses.yaml"
    return read_scan_poses(Path(root) / "scans" / name)
