"""A real recording (one camera image, lidar scans, calibration) as a scene folder.

``semcal real-scene`` and ``semcal kitti-scene`` both end in :func:`write_real_scene`, which writes
the scene folder contract of docs/CONTRACTS.md (kind ``real``). The map frame is the first scan's
lidar frame (z up for a level lidar); further scans are placed there from their given poses by
de-skew and ICP around the scan at the identity (:func:`semcal_ros.mapping.placement.placed_map`;
``scans/`` holds them as placed, de-skewed, with the refined poses). Point labels come
with the scans (SemanticKITTI ``.label`` files, a label file given per scan) or from the geometric
labeller; the label image from a segmenter, a given PNG or the first scan's point labels projected
through the true extrinsic (the ideal-label reference).

What the map keeps (the paper kept parked cars and removed only what moved): SemanticKITTI's
moving classes (252-259) are removed; with several geometrically labelled scans, vehicles that
moved between scans are relabelled moving (:func:`mark_moved_vehicles`) and removed too; parked
vehicles stay, and ``calibrator.yaml`` makes the engine count them
(``labels.parked_vehicles``). ``remove_vehicles`` removes every vehicle (a roadside map recorded
on another day has other parked cars than the image).

``calibrator.yaml`` carries what this sensor pair needs, worked out from the data and the initial
guess only: ``loss.crop_top`` leaves out the image rows above the highest map point the camera can
see from the initial pose, less a margin of the search's pitch bound; road and sidewalk are merged
(neither a lidar labeller nor an image segmenter draws that border reliably: the paper merged them
on KITTI).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import files, kitti, ply
from semcal_ros.io.scene_scans import write_scan_poses
from semcal_ros.engine.labels import (CITYSCAPES, CITYSCAPES_ID, DEFAULT_ALIGNMENT, INVALID, KITTI_ID,
                               MOVING_KITTI, SEMANTIC_KITTI, VEHICLE_KITTI, moving_id_of)
from semcal_ros.engine.pose import Pose

#: Scan file formats read by :func:`read_lidar_scan`.
SCAN_FORMATS = (".bin", ".pcd", ".ply")
#: ``cloud_labels`` values that are not a file.
LABEL_MODES = ("geometric", "semantickitti")


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


def label_geometric(cloud: LabelledCloud) -> np.ndarray:
    """SemanticKITTI ids from the geometric labeller (no network), its default parameters."""
    from semcal_ros.segmentation.geometric import label_scan

    return np.asarray(label_scan(cloud.xyz, cloud.extra.get("intensity")), np.uint16)


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


def scan_poses_in_map(scan_paths: list[Path], poses_path: Path | None,
                      kitti_tr: np.ndarray | None = None) -> list[np.ndarray]:
    """Each scan's lidar pose in the map frame (the first scan's lidar frame).

    ``poses_path``: a ``scans/poses.yaml``-format file (lidar poses in any world frame, entries
    matched to the scans by file name) or a KITTI ``poses.txt`` (cam0 poses, rows by the scan
    file's number, turned into lidar poses through ``kitti_tr``). One scan needs none.
    """
    from semcal_ros.io.scene_scans import read_scan_poses

    if poses_path is None:
        if len(scan_paths) > 1:
            raise ValueError(f"{len(scan_paths)} scans need --poses (where each scan was taken)")
        return [np.eye(4)]
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


def label_scans(scan_paths: list[Path], clouds: list[LabelledCloud], cloud_labels: list[str],
                poses: list[np.ndarray], label_distance: float = 0.3
                ) -> tuple[list[LabelledCloud], str, list[str]]:
    """The scans with SemanticKITTI labels: ``["geometric"]``, ``["semantickitti"]`` or one
    label file per scan. Returns the labelled scans, a description and notes for the user.

    semantickitti: a scan without its ``.label`` file takes, per point, the label of the nearest
    point of the labelled scans within ``label_distance`` (map frame); points with none that
    close are dropped (static structure is seen by several scans).
    """
    notes: list[str] = []
    if cloud_labels == ["geometric"]:
        out = [LabelledCloud(c.xyz, label_geometric(c), c.extra) for c in clouds]
        return out, "geometric labeller", notes
    if cloud_labels == ["semantickitti"]:
        paths = [semantickitti_label_path(p) for p in scan_paths]
        have = [i for i, lp in enumerate(paths) if lp.is_file()]
        if not have:
            raise ValueError(f"none of the scans has a SemanticKITTI label file "
                             f"(expected e.g. {paths[0]})")
        out: list[LabelledCloud | None] = [None] * len(clouds)
        for i in have:
            out[i] = LabelledCloud(clouds[i].xyz, read_point_labels(paths[i], len(clouds[i]),
                                                                    scan_paths[i]),
                                   clouds[i].extra)

        def in_map(i: int, xyz: np.ndarray) -> np.ndarray:
            return xyz @ poses[i][:3, :3].T + poses[i][:3, 3]

        sources = [in_map(i, out[i].xyz) for i in have]
        source_labels = [out[i].label for i in have]
        for i, cloud in enumerate(clouds):
            if out[i] is not None:
                continue
            got = transfer_labels(in_map(i, cloud.xyz), sources, source_labels, label_distance)
            keep = got > 0
            out[i] = LabelledCloud(cloud.xyz[keep], got[keep],
                                   {k: v[keep] for k, v in cloud.extra.items()})
            notes.append(f"scan {scan_paths[i].name}: no labels; labelled from the nearest "
                         f"labelled point within {label_distance} m ({100 * keep.mean():.1f} % "
                         "of its points), the rest dropped")
        return out, "SemanticKITTI label files", notes
    if any(c in LABEL_MODES for c in cloud_labels):
        raise ValueError("--cloud-labels: geometric or semantickitti stand alone, not with files")
    if len(cloud_labels) != len(clouds):
        raise ValueError(f"--cloud-labels: {len(cloud_labels)} label file(s) for {len(clouds)} "
                         "scan(s) (one per scan, or geometric / semantickitti)")
    out = []
    for path, scan, cloud in zip(cloud_labels, scan_paths, clouds):
        if not Path(path).is_file():
            raise FileNotFoundError(f"point label file not found: {path}")
        out.append(LabelledCloud(cloud.xyz, read_point_labels(path, len(cloud), scan),
                                 cloud.extra))
    return out, "label files " + ", ".join(Path(c).name for c in cloud_labels), notes


def mark_moved_vehicles(clouds: list[LabelledCloud], poses: list[np.ndarray],
                        moved_m: float = 1.0, seen_m: float = 1.5, cluster_m: float = 0.7,
                        min_points: int = 15) -> list[int]:
    """Relabel vehicles that moved between scans as SemanticKITTI moving classes (in place).

    Each scan's vehicle points are clustered (Open3D DBSCAN). A cluster moved if the scan
    farthest from it in the list saw that place (it has points, e.g. the ground, within
    ``seen_m`` of the cluster's centre, horizontally, map frame) but has no vehicle point within
    ``moved_m`` of it. A place the other scan did not see says nothing: the vehicle is kept.
    Returns the number of clusters relabelled per scan.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    if len(clouds) < 2:
        return [0] * len(clouds)
    vehicle_ids = np.array(VEHICLE_KITTI, np.uint16)
    in_map = [c.xyz @ p[:3, :3].T + p[:3, 3] for c, p in zip(clouds, poses)]
    trees = [cKDTree(x[:, :2]) for x in in_map]
    vehicle_trees = []
    for c, x in zip(clouds, in_map):
        sel = np.isin(c.label, vehicle_ids)
        vehicle_trees.append(cKDTree(x[sel, :2]) if sel.any() else None)
    moved_counts = []
    for i, cloud in enumerate(clouds):
        idx = np.flatnonzero(np.isin(cloud.label, vehicle_ids))
        count = 0
        if len(idx) >= min_points:
            other = max(range(len(clouds)), key=lambda j: abs(j - i))
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(in_map[i][idx]))
            cluster = np.asarray(pcd.cluster_dbscan(cluster_m, min_points))
            for k in range(int(cluster.max(initial=-1)) + 1):
                members = idx[cluster == k]
                centre = in_map[i][members, :2].mean(axis=0)
                seen = trees[other].query_ball_point(centre, seen_m, return_length=True) > 0
                near = (vehicle_trees[other] is not None and
                        vehicle_trees[other].query_ball_point(centre, moved_m,
                                                              return_length=True) > 0)
                if seen and not near:
                    cloud.label[members] = moving_id_of(cloud.label[members])
                    count += 1
        moved_counts.append(count)
    return moved_counts


def projected_truth_labels(cloud: LabelledCloud, t_cam_lidar: np.ndarray, camera: CameraModel,
                           fill_px: int = 6) -> np.ndarray:
    """A trainId image from labelled lidar points seen from the camera (an ideal-label target).

    Each point's SemanticKITTI class becomes its Cityscapes class (the default alignment); the
    nearest point wins a pixel, and empty pixels within ``fill_px`` of a labelled one take its
    label (scan lines are several pixels apart up close). Everything else is ignored (255).
    Built from the same lidar the map comes from, so it is free of segmentation errors: a
    reference for what the engine reaches with perfect labels.
    """
    import cv2

    lut = np.full(65536, INVALID, np.uint8)
    for kitti_name, city in DEFAULT_ALIGNMENT.items():
        lut[KITTI_ID[kitti_name]] = CITYSCAPES_ID[city]
    pts = cloud.xyz @ t_cam_lidar[:3, :3].T + t_cam_lidar[:3, 3]
    front = pts[:, 2] > 0.5
    uv, ok = camera.project(pts)
    ok &= front
    col = np.clip(np.round(uv[ok, 0]).astype(int), 0, camera.width - 1)
    row = np.clip(np.round(uv[ok, 1]).astype(int), 0, camera.height - 1)
    labels = lut[cloud.label[ok]]
    z = pts[ok, 2]
    order = np.argsort(-z)  # far first: the nearest point is written last and wins
    image = np.full((camera.height, camera.width), INVALID, np.uint8)
    image[row[order], col[order]] = labels[order]
    empty = (image == INVALID).astype(np.uint8)
    if empty.all():
        return image
    dist, nearest = cv2.distanceTransformWithLabels(empty, cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    seeds = np.zeros(int(nearest.max()) + 1, np.uint8)
    seeds[nearest[empty == 0]] = image[empty == 0]
    filled = seeds[nearest]
    return np.where((empty == 1) & (dist <= fill_px), filled, image).astype(np.uint8)



def reachable_crop_top(map_cloud: LabelledCloud, camera: CameraModel, initial: Pose,
                       margin_deg: float, min_points: int = 5) -> float:
    """Share of image rows from the top that no map point reaches, seen from ``initial``.

    The map's top edge in the image (the row of the ``min_points``-th highest projected point,
    so one stray point does not decide it) moved up by the rows ``margin_deg`` of pitch spans
    (the search may tilt the camera that far), rounded down to 1/100. Uses the initial guess
    only, never the truth.
    """
    pts = initial.transform_points(map_cloud.xyz)
    front = pts[:, 2] > 0.5
    uv, _ = camera.project(pts[front])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] < camera.height)
    if inside.sum() < min_points:
        return 0.0
    top = float(np.partition(uv[inside, 1], min_points - 1)[min_points - 1])
    rows = top - camera.fy * math.tan(math.radians(margin_deg))
    return max(0.0, math.floor(100.0 * rows / camera.height) / 100.0)


def label_shares(labels: np.ndarray, names: dict[int, str], skip: tuple[int, ...] = ()
                 ) -> dict[str, float]:
    """Share of each class (by name), largest first; ``skip`` ids are left out of the total."""
    values, counts = np.unique(labels, return_counts=True)
    keep = ~np.isin(values, skip)
    values, counts = values[keep], counts[keep]
    total = max(int(counts.sum()), 1)
    order = np.argsort(-counts)
    return {names.get(int(values[i]), str(int(values[i]))): round(float(counts[i]) / total, 4)
            for i in order}


@dataclass
class RealSceneInputs:
    """Everything :func:`write_real_scene` needs, already read and checked."""

    rgb: np.ndarray  # (H, W, 3) uint8 camera image
    camera: CameraModel
    scans: list[LabelledCloud]  # lidar frame, labelled
    scan_names: list[str]  # source file per scan (for scene.yaml)
    poses: list[np.ndarray]  # 4x4 lidar i in the map frame (= the first scan's lidar frame)
    stamps: list[float]
    t_cam_lidar: np.ndarray | None  # the true extrinsic, when known
    initial: Pose | None = None  # None: the truth perturbed (seed)
    cloud_labels: str = ""  # where the point labels came from
    label_notes: list[str] = field(default_factory=list)  # e.g. labels transferred to a scan
    scan_files: list[str] | None = None  # names under scans/ (default 000000.ply, ...)


@dataclass
class RealSceneOptions:
    d_max: float = 60.0  # m, points farther from the sensor are dropped
    voxel: float = 0.1  # m, map voxel size
    remove_vehicles: bool = False  # True: no vehicle in the map, vehicle pixels masked
    merge_road_sidewalk: bool = True
    crop_margin_deg: float = 5.0  # pitch margin of the crop_top row (the search's pitch bound)
    crop_radius: float = 0.0  # > 0: render.crop_radius in calibrator.yaml (m)
    seed: int = 0  # initial.yaml's perturbation
    kind: str = "real"
    camera_name: str = "camera"
    engine: dict | None = None  # a fixed engine group instead of the derived one (kitti-scene)


@dataclass
class RealSceneReport:
    folder: Path
    map_points: int
    scan_points: list[int]
    map_shares: dict[str, float]
    image_shares: dict[str, float]
    engine: dict
    moved_vehicles: list[int]
    removed_points: int
    labels_source: str
    seconds: float


def write_real_scene(inputs: RealSceneInputs, out: str | Path,
                     label_image: Callable[[np.ndarray], tuple[np.ndarray, str]],
                     options: RealSceneOptions = RealSceneOptions(),
                     extra_meta: dict | None = None) -> RealSceneReport:
    """Write the scene folder ``out`` (docs/CONTRACTS.md) for one camera image and its scans.

    ``label_image(rgb)`` returns the trainId label image and where it came from; it is called
    before anything is written, so a bad label image leaves no folder behind. A third item, when
    not None, is the segmenter's (H, W, 19) class probabilities: written as
    ``probabilities.npz`` (docs/CONTRACTS.md).
    """
    from semcal_ros.engine.pose import perturbed_initial

    start = time.perf_counter()
    out = Path(out)
    camera, rgb = inputs.camera, inputs.rgb
    if rgb.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"the image is {rgb.shape[1]}x{rgb.shape[0]}, the camera "
                         f"{camera.width}x{camera.height}")
    if inputs.t_cam_lidar is None and inputs.initial is None:
        raise ValueError("no extrinsic and no initial pose: give one of them")
    labels, labels_source, *more = label_image(rgb)
    probabilities = more[0] if more else None
    if labels.shape != (camera.height, camera.width):
        raise ValueError(f"label image is {labels.shape[1]}x{labels.shape[0]}, the camera "
                         f"image {camera.width}x{camera.height}")

    moved = [0] * len(inputs.scans)
    if inputs.cloud_labels == "geometric":
        moved = mark_moved_vehicles(inputs.scans, inputs.poses)
    # moving objects (and with remove_vehicles every vehicle) leave the scans before they are
    # placed: they win no voxel, and a map built again from scans/ is this map
    removed_ids = np.array(list(MOVING_KITTI) + (list(VEHICLE_KITTI) if options.remove_vehicles
                                                 else []), np.uint16)
    gone = [np.isin(c.label, removed_ids) for c in inputs.scans]
    scans = [c.select(~g) for c, g in zip(inputs.scans, gone)]
    removed_points = int(sum(g.sum() for g in gone))
    from semcal_ros.mapping.placement import placed_map  # de-skew + ICP around the anchor scan
    placed = placed_map(scans, inputs.poses, inputs.stamps, options.d_max, options.voxel)
    map_cloud = placed.map
    if len(map_cloud) == 0:
        raise ValueError("the map is empty (no labelled point within d_max)")

    truth = None
    if inputs.t_cam_lidar is not None:
        m = np.linalg.inv(inputs.t_cam_lidar)  # camera in the lidar (= map) frame
        truth = Pose.from_matrix(m[:3, :3], m[:3, 3])
    initial = inputs.initial or perturbed_initial(truth, np.random.default_rng(options.seed))
    engine = options.engine if options.engine is not None else derived_engine_settings(
        map_cloud, camera, initial, options)

    out.mkdir(parents=True, exist_ok=True)
    ply.write_ply(out / "map.ply", map_cloud)
    scan_dir = out / "scans"
    scan_dir.mkdir(exist_ok=True)
    names = inputs.scan_files or [f"{i:06d}.ply" for i in range(len(inputs.scans))]
    for name, cloud in zip(names, placed.scans):  # de-skewed, at their refined poses:
        ply.write_ply(scan_dir / name, cloud)      # a map built again from scans/ is map.ply
    write_scan_poses(scan_dir / "poses.yaml", names, np.array(inputs.stamps),
                     np.array(placed.poses), extra={"sources": list(inputs.scan_names)})
    files.write_label_image(out / "labels.png", labels)
    if probabilities is not None:
        from semcal_ros.segmentation.probabilities import write_probabilities

        write_probabilities(out / "probabilities.npz", probabilities)
    files.write_rgb_image(out / "image.png", rgb)
    files.write_camera_info(out / "camera_info.yaml", camera, name=options.camera_name)
    if truth is not None:
        files.write_pose(out / "ground_truth.yaml", truth)
    files.write_pose(out / "initial.yaml", initial)
    (out / "calibrator.yaml").write_text(calibrator_yaml(engine, options.engine is None))
    report = RealSceneReport(
        out, len(map_cloud), [len(c) for c in inputs.scans],
        label_shares(map_cloud.label, SEMANTIC_KITTI),
        label_shares(labels, CITYSCAPES, skip=(INVALID,)), engine, moved, removed_points,
        labels_source, time.perf_counter() - start)
    (out / "scene.yaml").write_text(yaml.safe_dump({
        "kind": options.kind,
        "scans": list(inputs.scan_names),
        "cloud_labels": inputs.cloud_labels,
        "cloud_label_notes": inputs.label_notes,
        "labels": labels_source,
        **({"probabilities": "probabilities.npz"} if probabilities is not None else {}),
        "ground_truth": truth is not None,
        "map_points": report.map_points,
        "scan_points": report.scan_points,
        "removed_points": report.removed_points,
        "moved_vehicle_clusters": moved,
        "remove_vehicles": options.remove_vehicles,
        "map_label_shares": report.map_shares,
        "image_label_shares": report.image_shares,
        "d_max": options.d_max,
        "voxel": options.voxel,
        **(extra_meta or {}),
        "seconds": round(report.seconds, 2),
    }, sort_keys=False))
    return report


def derived_engine_settings(map_cloud: LabelledCloud, camera: CameraModel, initial: Pose,
                            options: RealSceneOptions) -> dict:
    """The ``engine:`` group this sensor pair needs, from the data and the initial guess."""
    engine: dict = {"loss": {"crop_top": reachable_crop_top(map_cloud, camera, initial,
                                                            options.crop_margin_deg)}}
    labels: dict = {}
    if options.merge_road_sidewalk:
        labels["merge"] = ["sidewalk:road"]
    if not options.remove_vehicles:
        labels["parked_vehicles"] = True
    if labels:
        engine["labels"] = labels
    if options.crop_radius > 0:
        engine["render"] = {"crop_radius": options.crop_radius}
    return engine


def calibrator_yaml(engine: dict, derived: bool = True) -> str:
    """A calibrator parameter file holding only the engine settings this scene needs."""
    body = yaml.safe_dump({"calibrator": {"ros__parameters": {"engine": engine}}},
                          sort_keys=False, default_flow_style=None)
    if derived:
        head = ("# Written by semcal real-scene from the data and the initial guess:\n"
                "#   loss.crop_top: image rows above the highest map point seen from the initial\n"
                "#     pose, less the search's pitch bound, are left out (no lidar point reaches\n"
                "#     them);\n"
                "#   labels.merge sidewalk:road: neither labeller draws that border reliably;\n"
                "#   labels.parked_vehicles: parked vehicles are in the map and count (moving\n"
                "#     ones were removed); absent with --remove-vehicles.\n")
    else:
        head = ("# The paper's KITTI settings (Tsaregorodtsev et al. 2022, Sec. IV): only the bottom\n"
                "# half of the image, road and sidewalk merged in both domains, map cropped to 75 m\n"
                "# around the initial position.\n")
    return (head + "# Everything else: the engine's defaults (config/calibrator.yaml).\n"
            "# Use: semcal calibrate --config calibrator.yaml ...\n" + body)
