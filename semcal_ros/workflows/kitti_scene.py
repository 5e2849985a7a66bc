"""A KITTI odometry frame as a scene folder (docs/CONTRACTS.md): the paper's real KITTI case.

``semcal kitti-scene`` calls :func:`write_kitti_scene`, a thin caller of the generic
:func:`semcal_ros.workflows.real_scene.write_real_scene` (``semcal real-scene``): it finds the frame's
files in the sequence folder, and writes the paper's KITTI settings instead of derived ones. The
map frame is the lidar frame of the chosen frame's scan; every scan is placed there with the
ground-truth poses (``poses.txt`` through ``Tr``), limited to ``d_max``, voxel-downsampled with
the majority label per voxel; moving classes (252-259) are removed, parked vehicles stay. The
ground truth is the left colour camera (P2) of that frame, from ``P2`` and ``Tr``.
``calibrator.yaml`` holds what the paper did on KITTI: the bottom half of the image, road and
sidewalk merged, the map cropped to 75 m around the initial position, parked cars kept.

SemanticKITTI labels exist for some scans only (here 0-2 of 0-5). A scan without labels takes,
per point, the label of the nearest point of the labelled scans within ``label_distance``
(static structure is seen by several scans); points with no labelled point that close are
dropped. The command says how many points that labelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from semcal_ros.io import files, kitti
from semcal_ros.io.lidar_scans import read_lidar_scan
from semcal_ros.workflows.real_scene import (MAP_DEFAULTS, RealSceneInputs, RealSceneOptions,
                                             calibrator_yaml, write_real_scene)
from semcal_ros.workflows.scene_labels import (label_scans, projected_truth_labels,
                                               transfer_labels)

__all__ = ["KITTI_ENGINE_SETTINGS", "IMAGE_NAME", "parse_scans", "KittiSceneReport",
           "projected_truth_labels", "transfer_labels", "write_kitti_scene", "kitti_calibrator_yaml"]

#: The paper's KITTI settings as the ``engine:`` group of a calibrator parameter file.
KITTI_ENGINE_SETTINGS = {
    "loss": {"crop_top": 0.5},               # only the bottom half (the map is cut in height)
    "labels": {"merge": ["sidewalk:road"],   # road and sidewalk merged in both domains
               "parked_vehicles": True},     # parked cars kept (moving ones removed)
    "render": {"crop_radius": 75.0},         # map cropped to 75 m around the initial position
}
#: The left colour camera's folder (projection P2); its images set the camera size.
IMAGE_NAME = "image_2"


def parse_scans(text: str) -> list[int]:
    """``"0-5"``, ``"0,2,4"`` or ``"3"`` -> sorted scan indices."""
    out: set[int] = set()
    try:
        for part in text.split(","):
            lo, sep, hi = part.strip().partition("-")
            first, last = int(lo), int(hi) if sep else int(lo)
            if first < 0 or last < first:
                raise ValueError
            out.update(range(first, last + 1))
    except ValueError:
        raise ValueError(f"--scans '{text}': expected e.g. 0-5, 0,2,4 or 3") from None
    return sorted(out)


@dataclass
class KittiSceneReport:
    """What :func:`write_kitti_scene` did, for the command's output and scene.yaml."""

    folder: Path
    frame: int
    scans: list[int]
    labelled: list[int]
    transferred: dict[int, float] = field(default_factory=dict)  # scan -> share kept
    map_points: int = 0
    labels_source: str = ""
    seconds: float = 0.0


def write_kitti_scene(root: str | Path, frame: int, scans: list[int], out: str | Path,
                      label_image: Callable[[np.ndarray, str], tuple[np.ndarray, str]],
                      d_max: float = MAP_DEFAULTS.d_max, voxel: float = MAP_DEFAULTS.voxel,
                      label_distance: float = 0.3,
                      seed: int = 0, log: Callable[[str], None] = print) -> KittiSceneReport:
    """Write the scene folder ``out`` for ``frame`` of the KITTI sequence ``root``.

    ``label_image(rgb, image_path)`` returns the frame's trainId label image and a description
    of where it came from (a model, a file, projected ground truth); it is called after the
    inputs were checked and before the map is built.
    """
    root, out = Path(root), Path(out)
    if not root.is_dir():
        raise FileNotFoundError(f"KITTI folder not found: {root}")
    image_path = root / IMAGE_NAME / f"{frame:06d}.png"
    if not image_path.is_file():
        raise FileNotFoundError(f"{root}: no {IMAGE_NAME}/{frame:06d}.png for frame {frame}")
    for i in sorted({frame, *scans}):
        if not (root / "velodyne" / f"{i:06d}.bin").is_file():
            raise FileNotFoundError(f"{root}: no velodyne/{i:06d}.bin (scan {i})")
    calib_path = root / "calib.txt"
    calib = kitti.read_calib(calib_path)
    if "P2" not in calib:
        raise ValueError(f"{calib_path}: no 'P2' (projection of the left colour camera)")
    rgb = files.read_rgb_image(image_path)
    height, width = rgb.shape[:2]
    camera, t_cam_lidar = kitti.camera_from_calib(calib, width, height, "P2")
    cam_poses = kitti.read_poses(root / "poses.txt")
    if max(scans + [frame]) >= len(cam_poses):
        raise ValueError(f"{root / 'poses.txt'}: {len(cam_poses)} poses, scan "
                         f"{max(scans + [frame])} has none")
    lidar0 = kitti.lidar_poses(cam_poses, calib["Tr"])  # lidar i in the lidar frame of scan 0
    to_map = np.linalg.inv(lidar0[frame])  # map = lidar frame of the chosen frame
    poses = [to_map @ lidar0[i] for i in scans]
    scan_paths = [root / "velodyne" / f"{i:06d}.bin" for i in scans]
    labelled = [i for i in scans if (root / "labels" / f"{i:06d}.label").is_file()]
    if not labelled:
        raise ValueError(f"{root}: none of the scans {scans[0]}-{scans[-1]} has a "
                         "labels/NNNNNN.label file: the map needs SemanticKITTI labels")

    labels, labels_source = label_image(rgb, str(image_path))
    clouds = [read_lidar_scan(p) for p in scan_paths]
    raw_points = [len(c) for c in clouds]
    clouds, described, notes = label_scans(scan_paths, clouds, ["semantickitti"], poses,
                                           label_distance)
    report = KittiSceneReport(out, frame, scans, labelled, labels_source=labels_source)
    for i, cloud, n in zip(scans, clouds, raw_points):
        if i not in labelled:
            report.transferred[i] = len(cloud) / n
    inputs = RealSceneInputs(rgb, camera, clouds, [str(p) for p in scan_paths], poses,
                             [0.1 * i for i in scans],  # KITTI's 10 Hz; the map ignores them
                             t_cam_lidar, None, described, notes,
                             scan_files=[f"{i:06d}.ply" for i in scans])
    options = RealSceneOptions(d_max=d_max, voxel=voxel, seed=seed, kind="kitti",
                               camera_name="kitti_image_2", engine=KITTI_ENGINE_SETTINGS)
    written = write_real_scene(inputs, out, lambda _rgb: (labels, labels_source), options, {
        "source": str(root),
        "frame": frame,
        "scans": scans,
        "labelled_scans": labelled,
        "transferred_scans": {i: round(s, 4) for i, s in report.transferred.items()},
        "label_distance_m": label_distance,
    })
    report.map_points = written.map_points
    report.seconds = written.seconds
    return report


def kitti_calibrator_yaml() -> str:
    """The paper's KITTI settings as a calibrator parameter file (the engine group only)."""
    return calibrator_yaml(KITTI_ENGINE_SETTINGS, derived=False)
