"""Point labels of a recording's scans and the label images made from them (ROS-free).

The scans' SemanticKITTI ids come from a point labeller (:mod:`semcal_ros.workflows.labellers`)
or from label files; a scan without its file takes the label of the nearest labelled point.
Vehicles that moved between scans are relabelled moving; the first scan's labels projected
through the true extrinsic are the ideal-label reference image.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import (CITYSCAPES_ID, DEFAULT_ALIGNMENT, INVALID, KITTI_ID,
                                      VEHICLE_KITTI, moving_id_of)
from semcal_ros.io.lidar_scans import read_point_labels, semantickitti_label_path
from semcal_ros.segmentation.labellers import MODEL_FREE, make_labeller

if TYPE_CHECKING:  # geometric.py loads numba: imported by the labeller when built
    from semcal_ros.segmentation.geometric import GeometricParams

#: ``cloud_labels`` values that are not a file: a labeller that needs no model, or the
#: SemanticKITTI label files beside the scans.
LABEL_MODES = (*MODEL_FREE, "semantickitti")


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


def label_scans(scan_paths: list[Path], clouds: list[LabelledCloud], cloud_labels: list[str],
                poses: list[np.ndarray], label_distance: float = 0.3,
                geometric: GeometricParams | None = None
                ) -> tuple[list[LabelledCloud], str, list[str]]:
    """The scans with SemanticKITTI labels: a model-free labeller (``["geometric"]``),
    ``["semantickitti"]`` or one label file per scan. Returns the labelled scans, a description
    and notes for the user.

    semantickitti: a scan without its ``.label`` file takes, per point, the label of the nearest
    point of the labelled scans within ``label_distance`` (map frame); points with none that
    close are dropped (static structure is seen by several scans).
    """
    notes: list[str] = []
    if len(cloud_labels) == 1 and cloud_labels[0] in MODEL_FREE:
        label = make_labeller(cloud_labels[0], geometric=geometric)
        out = [LabelledCloud(c.xyz, label(c.xyz, c.extra.get("intensity")), c.extra)
               for c in clouds]
        return out, f"{cloud_labels[0]} labeller", notes
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
        raise ValueError(f"--cloud-labels: {' or '.join(LABEL_MODES)} stand alone, not with "
                         "files")
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
