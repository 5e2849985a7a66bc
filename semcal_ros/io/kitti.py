"""KITTI odometry and SemanticKITTI files: velodyne scans, point labels, poses and calibration.

Layout of one sequence (the odometry benchmark's, with SemanticKITTI labels beside the scans)::

    SEQ/velodyne/NNNNNN.bin   float32 x, y, z, reflectance per point (lidar frame)
    SEQ/labels/NNNNNN.label   uint32 per point: lower 16 bits class id, upper 16 bits instance id
    SEQ/poses.txt             one 3x4 row-major matrix per line: left camera (cam0) of frame i
                              in the cam0 frame of frame 0
    SEQ/calib.txt             ``P0:`` .. ``P3:`` (3x4 projections) and ``Tr:`` (velodyne -> cam0)
    SEQ/times.txt             optional, seconds since the start, one per scan

KITTI's ground-truth poses are of the camera, not the lidar, and their frame has y pointing down.
:func:`lidar_poses` turns them into lidar poses in a z-up map frame (the lidar frame of scan 0),
which is what the map builder expects.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud

if TYPE_CHECKING:
    from semcal_ros.engine.camera import CameraModel


def _require_file(path: str | Path, what: str) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    return path


def read_velodyne(path: str | Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, reflectance of one ``.bin`` scan. The file's size must be a
    whole number of 16-byte points (numpy alone reads a damaged 16 N + 3 bytes as N points),
    and the scan must hold a few distinct points (:func:`~semcal_ros.io.files.distinct_points_problem`)."""
    from semcal_ros.io.files import distinct_points_problem

    path = _require_file(path, "velodyne scan")
    size = path.stat().st_size
    if size % 16:
        raise ValueError(f"{path}: size {size} bytes is not a multiple of 16 "
                         "(expected float32 x, y, z, reflectance per point)")
    raw = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    problem = distinct_points_problem(raw[:, :3])
    if problem:
        raise ValueError(f"{path}: {problem}")
    return raw


def read_labels(path: str | Path) -> np.ndarray:
    """(N,) uint16 SemanticKITTI class ids of one ``.label`` file (instance ids masked off)."""
    path = _require_file(path, "label file")
    size = path.stat().st_size
    if size % 4:
        raise ValueError(f"{path}: size {size} bytes is not a multiple of 4 "
                         "(expected one uint32 label per point)")
    raw = np.fromfile(path, dtype="<u4")
    return (raw & 0xFFFF).astype(np.uint16)


def read_scan(bin_path: str | Path, label_path: str | Path | None = None) -> LabelledCloud:
    """One scan with reflectance as ``extra['intensity']`` and labels if a label file is given."""
    points = read_velodyne(bin_path)
    label = None
    if label_path is not None:
        label = read_labels(label_path)
        if len(label) != len(points):
            raise ValueError(f"{label_path}: {len(label)} labels for {len(points)} points "
                             f"in {bin_path}")
    return LabelledCloud(points[:, :3].astype(np.float64), label, {"intensity": points[:, 3]})


def read_poses(path: str | Path) -> np.ndarray:
    """(N, 4, 4) poses from a KITTI ``poses.txt`` (12 numbers per line, 3x4 row-major)."""
    path = _require_file(path, "poses file")
    try:
        rows = np.loadtxt(path, dtype=float, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: not a KITTI poses file ({exc})") from None
    if rows.shape[1] != 12:
        raise ValueError(f"{path}: expected 12 numbers per line, got {rows.shape[1]}")
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, :3, :] = rows.reshape(-1, 3, 4)
    return out


def read_key_values(path: str | Path, what: str = "calibration file") -> dict[str, np.ndarray]:
    """``KEY: numbers`` lines (KITTI calib files, the PJLab K/D/T text) as flat float arrays."""
    path = _require_file(path, what)
    out: dict[str, np.ndarray] = {}
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        key, sep, values = line.partition(":")
        if not sep:
            raise ValueError(f"{path}:{number}: expected 'KEY: numbers'")
        try:
            out[key.strip()] = np.array(values.split(), dtype=float)
        except ValueError:
            raise ValueError(f"{path}:{number}: '{key.strip()}' has non-numeric values") from None
    return out


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """``calib.txt`` entries: ``P0``..``P3`` as 3x4, ``Tr`` (velodyne -> cam0) as 4x4."""
    out: dict[str, np.ndarray] = {}
    for key, nums in read_key_values(path).items():
        if nums.size != 12:
            raise ValueError(f"{path}: '{key}' has {nums.size} numbers, expected 12")
        out[key] = nums.reshape(3, 4)
    if "Tr" not in out:
        raise ValueError(f"{path}: no 'Tr' (velodyne -> cam0) entry")
    tr = np.eye(4)
    tr[:3, :] = out["Tr"]
    out["Tr"] = tr
    return out


def lidar_poses(cam0_poses: np.ndarray, tr_velo_to_cam: np.ndarray,
                frame: str = "lidar0") -> np.ndarray:
    """Lidar poses from KITTI's camera poses.

    ``pose_i @ Tr`` maps lidar points of scan i into the cam0 frame of frame 0 (``frame="cam0"``),
    whose y axis points down. ``frame="lidar0"`` (default) re-expresses them in the lidar frame of
    scan 0, ``inv(Tr) @ pose_i @ Tr``: z up, so heights, crops and corridors mean what they say.
    """
    poses = np.asarray(cam0_poses, float) @ tr_velo_to_cam
    if frame == "cam0":
        return poses
    if frame == "lidar0":
        return np.linalg.inv(tr_velo_to_cam) @ poses
    raise ValueError(f"unknown KITTI map frame '{frame}' (use 'lidar0' or 'cam0')")


@dataclass(frozen=True)
class KittiSequence:
    """Files of one odometry sequence folder, scans paired with their poses by index."""

    root: Path
    scan_paths: list[Path]
    label_paths: list[Path | None]
    poses: np.ndarray  # (N, 4, 4) lidar in the map frame (see lidar_poses)
    stamps: np.ndarray  # (N,) seconds
    calib: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.scan_paths)

    def scan(self, i: int) -> LabelledCloud:
        return read_scan(self.scan_paths[i], self.label_paths[i])


def is_kitti_sequence(root: str | Path) -> bool:
    root = Path(root)
    return (root / "velodyne").is_dir() and (root / "poses.txt").is_file()


def open_sequence(root: str | Path, frame: str = "lidar0") -> KittiSequence:
    """Index a KITTI odometry folder; scans beyond the poses' rows are an error.

    Scans with no pose row are refused rather than dropped silently: the mismatch usually means a
    wrong poses file. Missing ``times.txt`` gives the sensor's 10 Hz (index * 0.1 s).
    """
    root = Path(root)
    if not (root / "velodyne").is_dir():
        raise FileNotFoundError(f"no velodyne/ folder in {root}")
    scans = sorted((root / "velodyne").glob("*.bin"))
    if not scans:
        raise ValueError(f"{root / 'velodyne'}: no .bin scans")
    calib = read_calib(root / "calib.txt")
    cam_poses = read_poses(root / "poses.txt")
    indices = []
    for p in scans:
        if not p.stem.isdigit():
            raise ValueError(f"{p}: scan file names must be frame numbers (NNNNNN.bin)")
        indices.append(int(p.stem))
    if max(indices) >= len(cam_poses):
        raise ValueError(f"{root}: scan {max(indices):06d} has no pose "
                         f"(poses.txt has {len(cam_poses)} rows)")
    times_path = root / "times.txt"
    if times_path.is_file():
        times = np.loadtxt(times_path, dtype=float, ndmin=1)
        if max(indices) >= len(times):
            raise ValueError(f"{times_path}: {len(times)} stamps, scan {max(indices):06d} has none")
    else:
        times = np.arange(max(indices) + 1) * 0.1
    labels: list[Path | None] = []
    for p in scans:
        lp = root / "labels" / (p.stem + ".label")
        labels.append(lp if lp.is_file() else None)
    idx = np.array(indices)
    return KittiSequence(root, scans, labels, lidar_poses(cam_poses[idx], calib["Tr"], frame),
                         times[idx], calib)


def camera_from_calib(calib: dict[str, np.ndarray], width: int, height: int,
                      camera: str = "P2") -> tuple["CameraModel", np.ndarray]:
    """A rectified KITTI camera: its model and its extrinsic ``T_cam_lidar`` (4x4).

    ``P = K [I | t]`` (rectified, no distortion): ``t = K^-1 P[:, 3]`` is the camera's offset from
    cam0, so a lidar point reaches the camera frame through ``[I | t] @ Tr``. ``Tr``'s rotation is
    stored with 10 digits and is not exactly orthonormal; it is projected onto the nearest
    rotation (SVD) so the pose is a proper rigid transform (the change is below 1e-4 deg).
    """
    from semcal_ros.engine.camera import CameraModel

    if camera not in calib:
        raise ValueError(f"calibration has no '{camera}' projection matrix "
                         f"(has: {', '.join(sorted(calib))})")
    p = np.asarray(calib[camera], float)
    k = p[:, :3]
    if abs(k[1, 0]) > 1e-9 or abs(k[2, 0]) > 1e-9 or abs(k[2, 1]) > 1e-9 or k[2, 2] != 1:
        raise ValueError(f"'{camera}' is not a rectified projection K [I | t]")
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(k, p[:, 3])
    tr = np.array(calib["Tr"], float)
    u, _, vt = np.linalg.svd(tr[:3, :3])
    tr[:3, :3] = u @ vt
    return CameraModel(width, height, k, np.zeros(5)), offset @ tr
