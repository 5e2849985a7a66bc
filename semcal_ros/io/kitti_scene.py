"""A KITTI odometry frame as a scene folder (docs/CONTRACTS.md): the paper's real KITTI case.

``semcal kitti-scene`` calls :func:`write_kitti_scene`. The map frame is the lidar frame of the
chosen frame's scan (z up, the camera near the origin); every scan is placed there with the
ground-truth poses (``poses.txt`` through ``Tr``), limited to ``d_max``, voxel-downsampled with
the majority label per voxel; dynamic classes stay in the map and the engine drops them (as it
does for every map). The ground truth is the left colour camera (P2) of that frame, from ``P2``
and ``Tr``. ``calibrator.yaml`` holds what the paper did on KITTI: the bottom half of the image,
road and sidewalk merged, the map cropped to 75 m around the initial position.

SemanticKITTI labels exist for some scans only (here 0-2 of 0-5). A scan without labels takes,
per point, the label of the nearest point of the labelled scans within ``label_distance``
(static structure is seen by several scans); points with no labelled point that close are
dropped. The command says how many points that labelled.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml

from semcal_ros.camera import CameraModel
from semcal_ros.cloud import LabelledCloud
from semcal_ros.io import files, kitti, ply
from semcal_ros.io.scene_scans import write_scan_poses
from semcal_ros.labels import CITYSCAPES_ID, DEFAULT_ALIGNMENT, INVALID, KITTI_ID
from semcal_ros.pose import Pose

#: The paper's KITTI settings as the ``engine:`` group of a calibrator parameter file.
KITTI_ENGINE_SETTINGS = {
    "loss": {"crop_top": 0.5},               # only the bottom half (the map is cut in height)
    "labels": {"merge": ["sidewalk:road"]},  # road and sidewalk merged in both domains
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


def projected_truth_labels(cloud: LabelledCloud, t_cam_lidar: np.ndarray, camera: CameraModel,
                           fill_px: int = 6) -> np.ndarray:
    """A trainId image from labelled lidar points seen from the camera (an ideal-label target).

    Each point's SemanticKITTI class becomes its Cityscapes class (the default alignment); the
    nearest point wins a pixel, and empty pixels within ``fill_px`` of a labelled one take its
    label (scan lines are several pixels apart up close). Everything else is ignored (255).
    Built from the same lidar the map comes from, so it is free of segmentation errors: a
    reference for what the engine reaches with perfect labels.
    """
    lut = np.full(65536, INVALID, np.uint8)
    for kitti_name, city in DEFAULT_ALIGNMENT.items():
        lut[KITTI_ID[kitti_name]] = CITYSCAPES_ID[city]
    pts = cloud.xyz @ t_cam_lidar[:3, :3].T + t_cam_lidar[:3, 3]
    uv, ok = camera.project(pts)
    ok &= pts[:, 2] > 0.5
    col = np.clip(np.round(uv[ok, 0]).astype(int), 0, camera.width - 1)
    row = np.clip(np.round(uv[ok, 1]).astype(int), 0, camera.height - 1)
    labels = lut[cloud.label[ok]]
    z = pts[ok, 2]
    order = np.argsort(-z)  # far first: the nearest point is written last and wins
    image = np.full((camera.height, camera.width), INVALID, np.uint8)
    image[row[order], col[order]] = labels[order]
    empty = (image == INVALID).astype(np.uint8)
    dist, nearest = cv2.distanceTransformWithLabels(empty, cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    seeds = np.zeros(int(nearest.max()) + 1, np.uint8)
    seeds[nearest[empty == 0]] = image[empty == 0]
    filled = seeds[nearest]
    return np.where((empty == 1) & (dist <= fill_px), filled, image).astype(np.uint8)


def transfer_labels(target: np.ndarray, sources: list[np.ndarray], source_labels: list[np.ndarray],
                    max_distance: float) -> np.ndarray:
    """Nearest labelled source point's label within ``max_distance`` (0 = none), map frame."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.vstack(sources))
    labels = np.concatenate(source_labels)
    dist, idx = tree.query(target, distance_upper_bound=max_distance, workers=1)
    out = np.zeros(len(target), np.uint16)
    hit = np.isfinite(dist)
    out[hit] = labels[idx[hit]]
    return out


def write_kitti_scene(root: str | Path, frame: int, scans: list[int], out: str | Path,
                      label_image: Callable[[np.ndarray, str], tuple[np.ndarray, str]],
                      d_max: float = 60.0, voxel: float = 0.1, label_distance: float = 0.3,
                      seed: int = 0, log: Callable[[str], None] = print) -> KittiSceneReport:
    """Write the scene folder ``out`` for ``frame`` of the KITTI sequence ``root``.

    ``label_image(rgb, image_path)`` returns the frame's trainId label image and a description
    of where it came from (a model, a file, projected ground truth); it is called after the
    inputs were checked and before the map is built.
    """
    from semcal_ros.mapping import MapBuildParams, ScanInput, build_map
    from semcal_ros.scenes.generate import perturbed_initial

    start = time.perf_counter()
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
    poses = {i: to_map @ lidar0[i] for i in scans}
    label_paths = {i: root / "labels" / f"{i:06d}.label" for i in scans}
    labelled = [i for i in scans if label_paths[i].is_file()]
    if not labelled:
        raise ValueError(f"{root}: none of the scans {scans[0]}-{scans[-1]} has a "
                         "labels/NNNNNN.label file: the map needs SemanticKITTI labels")

    labels, labels_source = label_image(rgb, str(image_path))
    if labels.shape != (height, width):
        raise ValueError(f"label image is {labels.shape[1]}x{labels.shape[0]}, the camera "
                         f"image {width}x{height}")

    clouds: dict[int, LabelledCloud] = {}
    for i in labelled:
        clouds[i] = kitti.read_scan(root / "velodyne" / f"{i:06d}.bin", label_paths[i])
    report = KittiSceneReport(out, frame, scans, labelled, labels_source=labels_source)

    def in_map(i: int, xyz: np.ndarray) -> np.ndarray:
        return xyz @ poses[i][:3, :3].T + poses[i][:3, 3]

    sources = [in_map(i, clouds[i].xyz) for i in labelled]
    source_labels = [clouds[i].label for i in labelled]
    for i in scans:
        if i in clouds:
            continue
        scan = kitti.read_scan(root / "velodyne" / f"{i:06d}.bin")
        got = transfer_labels(in_map(i, scan.xyz), sources, source_labels, label_distance)
        keep = got > 0
        clouds[i] = LabelledCloud(scan.xyz[keep], got[keep],
                                  {k: v[keep] for k, v in scan.extra.items()})
        report.transferred[i] = float(keep.mean())

    out.mkdir(parents=True, exist_ok=True)
    params = MapBuildParams(d_max=d_max, voxel=voxel, icp=False, remove_dynamic=False)
    stamps = {i: 0.1 * i for i in scans}  # KITTI's 10 Hz; the map does not depend on them
    result = build_map([ScanInput(clouds[i], poses[i], stamps[i], f"{i:06d}") for i in scans],
                       params)
    if result.skipped:
        raise ValueError(f"scans skipped by the map builder: {result.skipped}")
    ply.write_ply(out / "map.ply", result.map)
    report.map_points = len(result.map)

    scan_dir = out / "scans"
    scan_dir.mkdir(exist_ok=True)
    for i in scans:
        ply.write_ply(scan_dir / f"{i:06d}.ply", clouds[i])
    write_scan_poses(scan_dir / "poses.yaml", [f"{i:06d}.ply" for i in scans],
                     np.array([stamps[i] for i in scans]), np.array([poses[i] for i in scans]),
                     extra={"source": str(root)})

    truth_matrix = np.linalg.inv(t_cam_lidar)  # camera in the lidar (= map) frame
    truth = Pose.from_matrix(truth_matrix[:3, :3], truth_matrix[:3, 3])
    files.write_label_image(out / "labels.png", labels)
    files.write_rgb_image(out / "image.png", rgb)
    files.write_camera_info(out / "camera_info.yaml", camera, name="kitti_image_2")
    files.write_pose(out / "ground_truth.yaml", truth)
    initial = perturbed_initial(truth, np.random.default_rng(seed))
    files.write_pose(out / "initial.yaml", initial)
    (out / "calibrator.yaml").write_text(calibrator_yaml())
    report.seconds = time.perf_counter() - start
    (out / "scene.yaml").write_text(yaml.safe_dump({
        "kind": "kitti",
        "source": str(root),
        "frame": frame,
        "scans": scans,
        "labelled_scans": labelled,
        "transferred_scans": {i: round(s, 4) for i, s in report.transferred.items()},
        "label_distance_m": label_distance,
        "labels": labels_source,
        "map_points": report.map_points,
        "d_max": d_max,
        "voxel": voxel,
        "seconds": round(report.seconds, 2),
    }, sort_keys=False))
    return report


def calibrator_yaml() -> str:
    """The paper's KITTI settings as a calibrator parameter file (the engine group only)."""
    body = yaml.safe_dump({"calibrator": {"ros__parameters": {"engine": KITTI_ENGINE_SETTINGS}}},
                          sort_keys=False, default_flow_style=None)
    return ("# The paper's KITTI settings (Tsaregorodtsev et al. 2022, Sec. IV): only the bottom\n"
            "# half of the image, road and sidewalk merged in both domains, map cropped to 75 m\n"
            "# around the initial position. Everything else: the engine's defaults\n"
            "# (config/calibrator.yaml). Use: semcal calibrate --config calibrator.yaml ...\n"
            + body)
