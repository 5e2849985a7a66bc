"""Camera intrinsics and lidar->camera extrinsics from the calibration files real data comes with.

``semcal real-scene`` takes a ROS ``camera_info`` YAML and a ``T_cam_lidar`` YAML (the generic
form), or the recording's own calibration files through ``--calib`` (the shortcuts). Every reader
returns a :class:`CalibrationSource`: a camera model (its size may be unknown: KITTI's files do
not carry one, the image decides) and the 4x4 ``T_cam_lidar`` that maps a point of the lidar frame
into the camera's optical frame (x right, y down, z forward). Formats, detected from the content:

* KITTI odometry ``calib.txt``: ``P0``..``P3`` and ``Tr`` (velodyne -> cam0); the camera is a
  rectified ``P = K [I | t]`` (default ``P2``, the left colour camera), ``T = [I | K^-1 p4] Tr``.
* KITTI object calib: ``P2``, ``R0_rect``, ``Tr_velo_to_cam``; ``T = [I | K^-1 p4] R0 Tr``.
* PJLab ``calib.txt``: ``K`` (9 numbers), ``D`` (4 or 5: k1 k2 p1 p2 [k3]), ``T`` (12 or 16
  numbers, lidar -> camera, row-major).
* PJLab JSON (SensorsCalibration): ``*-intrinsic.json`` (``cam_K``, ``cam_dist``,
  ``img_dist_w``/``img_dist_h``) and ``*-extrinsic.json`` (``sensor_calib``, lidar -> camera);
  give both files.

Rotations stored with few digits are not exactly orthonormal; they are projected onto the nearest
rotation (SVD) so the ground truth is a proper rigid transform (the change is below 1e-4 deg on
the shared data).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from semcal_ros.engine.camera import CameraModel
from semcal_ros.io.files import load_yaml
from semcal_ros.io.kitti import read_key_values

#: How far a stored rotation may be from orthonormal (max |R^T R - I|) before it is refused.
ORTHONORMAL_TOLERANCE = 1e-3


@dataclass(frozen=True)
class CalibrationSource:
    """What one or more calibration files say. ``size`` None: the image gives the size."""

    k: np.ndarray | None = None  # 3x3
    d: np.ndarray | None = None  # plumb_bob k1, k2, p1, p2, k3
    size: tuple[int, int] | None = None  # (width, height) the intrinsics were made for
    t_cam_lidar: np.ndarray | None = None  # 4x4 lidar frame -> camera optical frame
    description: str = ""

    def merged(self, other: "CalibrationSource") -> "CalibrationSource":
        """This source completed by ``other`` (two files: intrinsics + extrinsic)."""
        for name in ("k", "t_cam_lidar"):
            if getattr(self, name) is not None and getattr(other, name) is not None:
                what = "camera intrinsics" if name == "k" else "extrinsic"
                raise ValueError(f"{self.description} and {other.description} both give the "
                                 f"{what}")
        pick = (lambda a, b: a if a is not None else b)
        return CalibrationSource(pick(self.k, other.k), pick(self.d, other.d),
                                 pick(self.size, other.size),
                                 pick(self.t_cam_lidar, other.t_cam_lidar),
                                 " + ".join(s for s in (self.description, other.description) if s))

    def camera(self, width: int, height: int, where: str) -> CameraModel:
        """The camera for an image of ``width`` x ``height``; a stated size must match it."""
        if self.k is None:
            raise ValueError(f"{where}: no camera intrinsics")
        if self.size is not None and self.size != (width, height):
            raise ValueError(f"{where}: the calibration is for {self.size[0]}x{self.size[1]} "
                             f"images, the image is {width}x{height}")
        d = self.d if self.d is not None else np.zeros(5)
        return CameraModel(width, height, self.k, d)


def rigid(matrix: np.ndarray, where: str) -> np.ndarray:
    """A 4x4 rigid transform from 12 (3x4) or 16 numbers, its rotation made exactly orthonormal."""
    m = np.asarray(matrix, dtype=float).ravel()
    if m.size not in (12, 16) or not np.all(np.isfinite(m)):
        raise ValueError(f"{where}: expected 12 (3x4) or 16 (4x4) finite numbers, got {m.size}")
    out = np.eye(4)
    out[:3, :] = m[:12].reshape(3, 4)
    if m.size == 16 and not np.allclose(m[12:], [0, 0, 0, 1], atol=1e-9):
        raise ValueError(f"{where}: last row of a rigid transform must be 0 0 0 1")
    r = out[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > ORTHONORMAL_TOLERANCE or np.linalg.det(r) <= 0:
        raise ValueError(f"{where}: the rotation part is not a rotation matrix")
    u, _, vt = np.linalg.svd(r)
    out[:3, :3] = u @ vt
    return out


def read_extrinsic_yaml(path: str | Path) -> np.ndarray:
    """``T_cam_lidar`` (4x4 nested list, or 16/12 numbers row-major) from a YAML file."""
    data = load_yaml(path, "extrinsic")
    if "T_cam_lidar" not in data:
        raise ValueError(f"{path}: expected a mapping with 'T_cam_lidar' (4x4, lidar -> camera)")
    try:
        values = np.asarray(data["T_cam_lidar"], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: T_cam_lidar is not a numeric 4x4 matrix") from None
    return rigid(values, f"{path}: T_cam_lidar")


def write_extrinsic_yaml(path: str | Path, t_cam_lidar: np.ndarray) -> None:
    """The generic form's ``T.yaml``."""
    rows = [[float(v) for v in row] for row in np.asarray(t_cam_lidar, float)]
    Path(path).write_text("# lidar frame -> camera optical frame (x right, y down, z forward)\n"
                          + yaml.safe_dump({"T_cam_lidar": rows}, default_flow_style=None))


def _rectified(p: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """K and the camera's offset (4x4) from a rectified KITTI projection ``K [I | t]``."""
    p = p.reshape(3, 4)
    k = p[:, :3]
    if abs(k[1, 0]) > 1e-9 or abs(k[2, 0]) > 1e-9 or abs(k[2, 1]) > 1e-9 or k[2, 2] != 1:
        raise ValueError(f"{where} is not a rectified projection K [I | t]")
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(k, p[:, 3])
    return k.copy(), offset


def read_text_calib(path: str | Path, projection: str = "P2") -> CalibrationSource:
    """A KITTI odometry, KITTI object or PJLab ``calib.txt`` (detected from its keys)."""
    path = Path(path)
    entries = read_key_values(path)

    def need(key: str, size: int) -> np.ndarray:
        if key not in entries:
            raise ValueError(f"{path}: no '{key}'")
        if entries[key].size != size:
            raise ValueError(f"{path}: '{key}' has {entries[key].size} numbers, expected {size}")
        return entries[key]

    if "Tr" in entries or "Tr_velo_to_cam" in entries:  # KITTI
        object_calib = "Tr_velo_to_cam" in entries
        tr = rigid(need("Tr_velo_to_cam" if object_calib else "Tr", 12), f"{path}: Tr")
        if projection not in entries:
            raise ValueError(f"{path}: no '{projection}' (projection of the camera; has "
                             f"{', '.join(sorted(entries))})")
        k, offset = _rectified(need(projection, 12), f"{path}: '{projection}'")
        if object_calib:  # points reach the rectified frame through R0_rect
            r0 = np.eye(4)
            r0[:3, :3] = rigid(np.c_[need("R0_rect", 9).reshape(3, 3), np.zeros(3)],
                               f"{path}: R0_rect")[:3, :3]
            return CalibrationSource(k, np.zeros(5), None, offset @ r0 @ tr,
                                     f"KITTI object calib {path.name} ({projection})")
        return CalibrationSource(k, np.zeros(5), None, offset @ tr,
                                 f"KITTI odometry calib {path.name} ({projection})")
    if "K" in entries:  # PJLab: K, D, T
        k = need("K", 9).reshape(3, 3)
        d = entries.get("D", np.zeros(5))
        if d.size not in (4, 5):
            raise ValueError(f"{path}: 'D' has {d.size} numbers, expected 4 or 5 "
                             "(k1 k2 p1 p2 [k3])")
        t = rigid(entries["T"], f"{path}: T") if "T" in entries else None
        return CalibrationSource(k, np.r_[d, np.zeros(5 - d.size)], None, t,
                                 f"K/D/T calib {path.name}")
    raise ValueError(f"{path}: unknown calibration format (expected KITTI P2 + Tr, KITTI "
                     f"object P2 + R0_rect + Tr_velo_to_cam, or K, D, T; has "
                     f"{', '.join(sorted(entries)) or 'nothing'})")


def _json_matrix(node: object, where: str) -> np.ndarray:
    data = node.get("data") if isinstance(node, dict) else None
    if data is None:
        raise ValueError(f"{where}: expected {{rows, cols, data}}")
    try:
        return np.asarray(data, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: 'data' is not a numeric matrix") from None


def read_json_calib(path: str | Path) -> CalibrationSource:
    """A PJLab (SensorsCalibration) intrinsic or extrinsic JSON file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: invalid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict) or len(data) != 1 or not isinstance(
            next(iter(data.values())), dict):
        raise ValueError(f"{path}: expected one named calibration object")
    name, body = next(iter(data.items()))
    param = body.get("param")
    if not isinstance(param, dict):
        raise ValueError(f"{path}: '{name}' has no 'param'")
    if "cam_K" in param:
        k = _json_matrix(param["cam_K"], f"{path}: cam_K").reshape(-1)
        if k.size != 9:
            raise ValueError(f"{path}: cam_K has {k.size} numbers, expected 9")
        d = _json_matrix(param.get("cam_dist", {"data": [0.0] * 5}), f"{path}: cam_dist").ravel()
        if d.size not in (4, 5):
            raise ValueError(f"{path}: cam_dist has {d.size} numbers, expected 4 or 5")
        size = None
        if "img_dist_w" in param and "img_dist_h" in param:
            size = (int(param["img_dist_w"]), int(param["img_dist_h"]))
        return CalibrationSource(k.reshape(3, 3), np.r_[d, np.zeros(5 - d.size)], size, None,
                                 f"intrinsic JSON {path.name}")
    if "sensor_calib" in param:
        t = rigid(_json_matrix(param["sensor_calib"], f"{path}: sensor_calib"),
                  f"{path}: sensor_calib")
        return CalibrationSource(t_cam_lidar=t, description=f"extrinsic JSON {path.name}")
    raise ValueError(f"{path}: '{name}' has neither cam_K (intrinsics) nor sensor_calib "
                     "(extrinsic)")


def read_calibration(paths: list[str | Path], projection: str = "P2") -> CalibrationSource:
    """One source from one or more calibration files (text or JSON, see the module docstring)."""
    out = CalibrationSource()
    for raw in paths:
        path = Path(raw)
        if not path.is_file():
            raise FileNotFoundError(f"calibration file not found: {path}")
        if path.suffix.lower() == ".json":
            source = read_json_calib(path)
        elif path.suffix.lower() in (".txt", ""):
            source = read_text_calib(path, projection)
        else:
            raise ValueError(f"{path}: unknown calibration format '{path.suffix}' (expected a "
                             "KITTI or K/D/T .txt, or a SensorsCalibration .json)")
        out = out.merged(source)
    return out
