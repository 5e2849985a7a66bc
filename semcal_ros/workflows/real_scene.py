"""A real recording (one camera image, lidar scans, calibration) as a scene folder (ROS-free).

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
on KITTI); ``loss.blind_rows`` is written where the lidar's rings lie far apart on the ground the
camera looks at (:func:`near_ground_gap_deg`): there the road between and below them is not
drawn, yet it is there, and the likelihood would count it as "nothing drawn".
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
from semcal_ros.engine.labels import (CITYSCAPES, INVALID, KITTI_ID, MOVING_KITTI,
                                      SEMANTIC_KITTI, VEHICLE_KITTI)
from semcal_ros.engine.pose import Pose
from semcal_ros.io import files, ply
from semcal_ros.io.scene_scans import write_scan_poses
from semcal_ros.mapping import MapBuildParams
from semcal_ros.workflows.scene_labels import label_shares, mark_moved_vehicles

#: The map builder's defaults (``map_builder``'s ``mapping.*``): the one source of a scene map's
#: ``d_max`` and ``voxel`` when the command is not given them.
MAP_DEFAULTS = MapBuildParams()

#: ``loss.blind_rows`` for a map whose near ground rings lie more than
#: :data:`SPARSE_GROUND_GAP_DEG` apart (docs/engine.md "The lidar's blind zone": 0.2 measured on
#: PJLab's frames, whose lidar's lowest rings are 6 and 5 deg apart; KITTI's HDL-64E at most 0.58)
SPARSE_GROUND_BLIND_ROWS = 0.2
SPARSE_GROUND_GAP_DEG = 2.0
GROUND_KITTI = tuple(KITTI_ID[k] for k in ("road", "parking", "sidewalk", "other-ground",
                                           "terrain"))


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


def near_ground_gap_deg(map_cloud: LabelledCloud, camera: CameraModel, initial: Pose,
                        below_deg: float = 5.0, max_range: float = 30.0,
                        min_points: int = 50) -> float:
    """Largest gap (deg) between the elevations of the near ground points ahead of the camera.

    Elevation is seen from the map's origin (the anchor scan's lidar), over the ground-labelled
    points (:data:`GROUND_KITTI`) more than ``below_deg`` below it, within ``max_range`` m, that
    fall in the image's columns from the initial pose (so a gap behind the camera does not
    count; 5 deg keeps far-field occlusions by cars out). On a lidar with rings a fraction of a
    degree apart (or a map of several scans) this is under 1 deg; PJLab's lowest rings are 6 deg
    apart. 0 with fewer than ``min_points`` such points (nothing to judge by).
    """
    ground = np.isin(map_cloud.label, GROUND_KITTI)
    xyz = map_cloud.xyz[ground]
    pts = initial.transform_points(xyz)
    front = pts[:, 2] > 0.5
    uv, _ = camera.project(pts[front])
    ahead = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width)
    xyz = xyz[front][ahead]
    rng = np.hypot(xyz[:, 0], xyz[:, 1])
    elevation = np.degrees(np.arctan2(xyz[:, 2], rng))
    elevation = np.sort(elevation[(elevation < -below_deg) & (rng < max_range)])
    if len(elevation) < min_points:
        return 0.0
    return float(np.max(np.diff(elevation)))


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
    # the registered point labeller that labelled the scans (None: label files): its vehicles
    # are not told moving from parked, so the ones that moved between scans are marked here
    labeller: str | None = None


@dataclass
class RealSceneOptions:
    d_max: float = MAP_DEFAULTS.d_max  # m, points farther from the sensor are dropped
    voxel: float = MAP_DEFAULTS.voxel  # m, map voxel size
    remove_vehicles: bool = False  # True: no vehicle in the map, vehicle pixels masked
    merge_road_sidewalk: bool = True
    crop_margin_deg: float = 5.0  # pitch margin of the crop_top row (the search's pitch bound)
    crop_radius: float = 0.0  # > 0: render.crop_radius in calibrator.yaml (m)
    # loss.blind_rows in calibrator.yaml (the lidar's blind zone); None: from the data
    # (SPARSE_GROUND_BLIND_ROWS where near_ground_gap_deg > SPARSE_GROUND_GAP_DEG, else none)
    blind_rows: float | None = None
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
    ground_gap_deg: float = 0.0  # near_ground_gap_deg: the near ground rings' largest gap


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
    if inputs.labeller is not None:
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
    ground_gap = near_ground_gap_deg(map_cloud, camera, initial)
    engine = options.engine if options.engine is not None else derived_engine_settings(
        map_cloud, camera, initial, options, ground_gap)

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
        labels_source, time.perf_counter() - start, ground_gap)
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
                            options: RealSceneOptions, ground_gap: float | None = None) -> dict:
    """The ``engine:`` group this sensor pair needs, from the data and the initial guess
    (``ground_gap``: :func:`near_ground_gap_deg`, computed here when not given)."""
    engine: dict = {"loss": {"crop_top": reachable_crop_top(map_cloud, camera, initial,
                                                            options.crop_margin_deg)}}
    blind_rows = options.blind_rows
    if blind_rows is None:
        if ground_gap is None:
            ground_gap = near_ground_gap_deg(map_cloud, camera, initial)
        blind_rows = SPARSE_GROUND_BLIND_ROWS if ground_gap > SPARSE_GROUND_GAP_DEG else 0.0
    if blind_rows > 0:
        engine["loss"]["blind_rows"] = blind_rows
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
                "#     ones were removed); absent with --remove-vehicles;\n"
                "#   loss.blind_rows (when present): the lidar's near ground rings lie more than\n"
                f"#     {SPARSE_GROUND_GAP_DEG:g} deg apart ahead of the camera, so the road below\n"
                "#     its lowest drawn point is left out of the likelihood (or --blind-rows\n"
                "#     was given).\n")
    else:
        head = ("# The paper's KITTI settings (Tsaregorodtsev et al. 2022, Sec. IV): only the bottom\n"
                "# half of the image, road and sidewalk merged in both domains, map cropped to 75 m\n"
                "# around the initial position.\n")
    return (head + "# Everything else: the engine's defaults (config/calibrator.yaml).\n"
            "# Use: semcal calibrate --config calibrator.yaml ...\n" + body)
