"""Lidar scan files of a recording: a scan in its lidar frame (KITTI ``.bin``, ``.pcd``,
``.ply``), its SemanticKITTI point labels, and where each scan was taken (a ``scans/poses.yaml``
table or a KITTI ``poses.txt``). Formats only; what a scene makes of them is
:mod:`semcal_ros.workflows.real_scene`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import kitti, ply

#: Scan file formats read by :func:`read_lidar_scan`.
SCAN_FORMATS = (".bin", ".pcd", ".ply")


def read_lidar_scan(path: str | Path) -> LabelledCloud:
    """A scan in its lidar frame: KITTI ``.bin``, ``.pcd`` (any encoding) or ``.ply``; intensity
    as ``extra['intensity']`` when the file has one, labels when it carries them."""
    from semcal_ros.io.pcd import INTENSITY_FIELDS, read_pcd

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SCAN_FORMATS:
        raise ValueError(f"{path}: unknown scan format '{path.suffix}' (expected "
                         f"{', '.join(SCAN_FORMATS)})")
    if not path.is_file():
        raise FileNotFoundError(f"scan not found: {path}")
    if suffix == ".bin":
        cloud = kitti.read_scan(path)
    elif suffix == ".pcd":
        cloud = read_pcd(path)
    else:
        cloud = ply.read_ply(path, require_label=False)
        name = next((f for f in INTENSITY_FIELDS if f in cloud.extra), None)
        if name is not None and name != "intensity":
            cloud.extra["intensity"] = cloud.extra.pop(name)
    if len(cloud) == 0:
        raise ValueError(f"{path}: the scan has no points")
    return cloud.finite()


def semantickitti_label_path(scan_path: Path) -> Path:
    """``SEQ/velodyne/NNNNNN.bin`` -> ``SEQ/labels/NNNNNN.label`` (SemanticKITTI's layout)."""
    return scan_path.parent.parent / "labels" / (scan_path.stem + ".label")


def read_point_labels(path: str | Path, n_points: int, scan: str | Path) -> np.ndarray:
    """SemanticKITTI ids from a ``.label`` file or a labelled ``.ply`` of the same scan."""
    path = Path(path)
    if path.suffix.lower() == ".label":
        labels = kitti.read_labels(path)
    elif path.suffix.lower() == ".ply":
        labels = ply.read_ply(path).label
    else:
        raise ValueError(f"{path}: unknown point label format '{path.suffix}' (expected a "
                         "SemanticKITTI .label or a .ply with a 'label' property)")
    if len(labels) != n_points:
        raise ValueError(f"{path}: {len(labels)} labels for the {n_points} points of {scan}")
    return labels.astype(np.uint16)


def scan_poses_in_map(scan_paths: list[Path], poses_path: Path | None,
                      kitti_tr: np.ndarray | None = None) -> list[np.ndarray] | None:
    """Each scan's lidar pose in the map frame (the first scan's lidar frame).

    ``poses_path``: a ``scans/poses.yaml``-format file (lidar poses in any world frame, entries
    matched to the scans by file name) or a KITTI ``poses.txt`` (cam0 poses, rows by the scan
    file's number, turned into lidar poses through ``kitti_tr``). One scan needs none; several
    without a file: None (the caller registers them, :mod:`semcal_ros.mapping.odometry`).
    """
    from semcal_ros.io.scene_scans import read_scan_poses

    if poses_path is None:
        return None if len(scan_paths) > 1 else [np.eye(4)]
    poses_path = Path(poses_path)
    if not poses_path.is_file():
        raise FileNotFoundError(f"poses file not found: {poses_path}")
    if poses_path.suffix.lower() == ".txt":
        if kitti_tr is None:
            raise ValueError(f"{poses_path}: KITTI poses are of the camera; they need a KITTI "
                             "calib with Tr (--calib)")
        cam = kitti.read_poses(poses_path)
        world = []
        for path in scan_paths:
            if not path.stem.isdigit():
                raise ValueError(f"{path}: with KITTI poses.txt scan names must be frame "
                                 "numbers (NNNNNN.bin)")
            if int(path.stem) >= len(cam):
                raise ValueError(f"{poses_path}: {len(cam)} poses, scan {path.name} has none")
            world.append(kitti.lidar_poses(cam[int(path.stem)][None], kitti_tr)[0])
    else:
        table = read_scan_poses(poses_path)
        by_name = {f.name: p for f, p in zip(table.files, table.poses)}
        missing = [p.name for p in scan_paths if p.name not in by_name]
        if missing:
            raise ValueError(f"{poses_path}: no pose for {', '.join(missing)}")
        world = [by_name[p.name] for p in scan_paths]
    to_map = np.linalg.inv(world[0])
    return [to_map @ w for w in world]
