"""Per-point filters of the map builder: validity, range, voxel grid, dynamic classes, crop.

Each takes and returns a :class:`~semcal_ros.engine.cloud.LabelledCloud`, so the builder composes them
and tests can check each alone.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
from scipy.spatial import cKDTree

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import KITTI_ID
from semcal_ros.mapping import kernels

#: SemanticKITTI "unlabeled" (0): loses every voxel vote against a real class.
UNLABELED = KITTI_ID["unlabeled"]


def as_scan_cloud(data: Any, what: str = "scan") -> LabelledCloud:
    """A scan as a LabelledCloud from a LabelledCloud, a structured array or a dict of fields.

    Live scans arrive as structured arrays (PointCloud2 fields) whose layout depends on the
    driver; this is the one place that checks they carry x, y and z, so a bad scan fails with a
    message that names the missing field rather than a ``KeyError`` deep inside registration.
    """
    if isinstance(data, LabelledCloud):
        return data
    if isinstance(data, np.ndarray) and data.dtype.names:
        names = data.dtype.names
        fields: Mapping[str, np.ndarray] = {n: data[n] for n in names}
    elif isinstance(data, Mapping):
        names = tuple(data.keys())
        fields = data
    else:
        raise ValueError(f"{what}: expected a LabelledCloud, a structured array or a dict of "
                         f"fields, got {type(data).__name__}")
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        raise ValueError(f"{what} has no {', '.join(missing)} field "
                         f"(fields: {', '.join(names) or 'none'})")
    xyz = np.stack([np.asarray(fields[n], dtype=np.float64).reshape(-1) for n in "xyz"], axis=1)
    label = None
    if "label" in fields:
        label = np.asarray(fields["label"]).reshape(-1).astype(np.uint32) & 0xFFFF
        label = label.astype(np.uint16)
    extra = {}
    if "intensity" in fields:
        extra["intensity"] = np.asarray(fields["intensity"], dtype=np.float32).reshape(-1)
    for name in ("t", "time", "timestamp"):  # per-point time for de-skew (deskew.TIME_FIELDS)
        if name in fields:
            extra[name] = np.asarray(fields[name], dtype=np.float64).reshape(-1)
            break
    return LabelledCloud(xyz, label, extra)


def range_filter(cloud: LabelledCloud, d_max: float, d_min: float = 0.0) -> LabelledCloud:
    """Finite points with d_min <= distance from the sensor (lidar frame origin) <= d_max.

    Far points are dropped before anything else (the paper's d_max, 50-75 m): a small heading
    error moves them by more than the voxel size, so they blur the map more than they fill it.
    """
    xyz = cloud.xyz
    d2 = np.einsum("ij,ij->i", xyz, xyz)
    keep = np.isfinite(d2) & (d2 <= d_max * d_max) & (d2 >= d_min * d_min)
    return cloud if keep.all() else cloud.select(keep)


_NO_LABEL = np.zeros(0, np.uint16)  # an unlabelled cloud's label argument of the kernel


def _float_extras(extra: Mapping[str, np.ndarray], n: int) -> tuple[list[str], np.ndarray]:
    """The float fields the voxel grid averages (names, (n, E) columns). A single field (a
    map's intensity) is passed as it is, a view: stacking it into float64 cost a quarter of the
    voxel grid of a merged cloud; the kernel sums it in float64 either way."""
    names = [name for name, values in extra.items()
             if values.ndim == 1 and np.issubdtype(values.dtype, np.floating)]
    if not names:
        return names, np.zeros((n, 0))
    if len(names) == 1 and extra[names[0]].dtype in (np.float32, np.float64):
        return names, np.ascontiguousarray(extra[names[0]]).reshape(n, 1)
    return names, np.stack([extra[k].astype(np.float64) for k in names], axis=1)


def voxel_downsample(cloud: LabelledCloud, voxel: float) -> LabelledCloud:
    """One point per occupied voxel, with the voxel's majority label (the map's voxel grid).

    The same rule as :func:`voxel_downsample_sorted` (the readable definition, below), computed
    by a compiled one-pass hash grid (``kernels.voxel_majority``): 2-3x faster on a scan, and
    O(N) instead of a sort. Voxels come in the order of their first point.
    """
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    xyz = cloud.xyz
    n = len(xyz)
    if n == 0:
        return LabelledCloud(np.zeros((0, 3)), None if cloud.label is None
                             else np.zeros(0, np.uint16))
    if not np.issubdtype(xyz.dtype, np.floating):
        xyz = xyz.astype(np.float64)
    if not kernels.span(xyz) / voxel < 2.0 ** 20:  # cells are packed 21 bits per axis
        raise ValueError(f"voxel grid too large for {voxel} m cells; "
                         "points far apart or a tiny voxel size")
    if cloud.label is None:
        ids, classes, table = _NO_LABEL, np.zeros(1, np.int64), np.zeros(1, np.int64)
    else:  # class ids -> 0..k-1 through a table, looked up in the kernel
        ids = cloud.label
        present = np.bincount(ids, minlength=1)
        classes = np.flatnonzero(present)
        table = np.zeros(len(present), np.int64)
        table[classes] = np.arange(len(classes))
    names, extra = _float_extras(cloud.extra, n)
    points, best, means = kernels.voxel_majority(
        np.ascontiguousarray(xyz), xyz.dtype.type(voxel), ids, table, len(classes),
        classes != UNLABELED if cloud.label is not None else np.ones(1, np.bool_), extra)
    label = None if cloud.label is None else classes[best].astype(np.uint16)
    return LabelledCloud(points, label, {k: means[:, j].astype(cloud.extra[k].dtype)
                                         for j, k in enumerate(names)})


def voxel_downsample_sorted(cloud: LabelledCloud, voxel: float) -> LabelledCloud:
    """One point per occupied voxel, with the voxel's majority label (readable definition).

    The point is the centroid of the majority class's points in the voxel, so class borders stay
    sharp and each point lies on a surface of its class. Done in numpy because Open3D's
    ``voxel_down_sample`` averages every attribute, which turns label ids into meaningless means.
    ``unlabeled`` (0) only wins a voxel in which no point has a class, so unlabelled scans (KITTI
    has labels for some scans only) fill gaps without overwriting classes; other ties go to the
    smaller id. Unlabelled clouds get plain centroids. Float extra fields (intensity, normal
    components) are averaged over the same points as the centroid; other extras are dropped.
    Cells are computed in the cloud's own precision (float32 points are binned as float32 numbers)
    and centroids summed in float64, so a float32 cloud loses nothing to the averaging. The grid
    is anchored at the coordinate origin: callers that want it elsewhere shift the points.
    Voxels come in the order of their keys. :func:`voxel_downsample` computes the same.
    """
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    xyz = cloud.xyz
    n = len(xyz)
    if n == 0:
        return LabelledCloud(np.zeros((0, 3)), None if cloud.label is None
                             else np.zeros(0, np.uint16))
    if cloud.label is None:
        classes, class_index = np.zeros(1, np.int64), 0
    else:  # class ids -> 0..k-1 through a table (a sort of the labels costs 20x more)
        present = np.bincount(cloud.label, minlength=1)
        classes = np.flatnonzero(present)
        table = np.zeros(len(present), np.int64)
        table[classes] = np.arange(len(classes))
        class_index = table[cloud.label]
    n_classes = len(classes)
    key = np.zeros(n, np.int64)
    for axis in range(3):  # column by column: (N, 3) reductions along axis 0 are slow
        cell = np.floor(xyz[:, axis] / voxel).astype(np.int64)
        cell -= cell.min()
        span = int(cell.max()) + 1
        if float(key.max() if axis else 0) * span * n_classes >= 2.0 ** 62:
            raise ValueError(f"voxel grid too large for {voxel} m cells; "
                             "points far apart or a tiny voxel size")
        key = key * span + cell
    key = key * n_classes + class_index
    # one sort; groups are (voxel, class) runs of the sorted keys
    order = np.argsort(key)
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    counts = np.diff(np.r_[starts, n])
    groups = sorted_key[starts]
    group_voxel, group_class = groups // n_classes, groups % n_classes
    # rank within a voxel: labelled classes first, then votes, then the smaller id
    score = counts + (classes[group_class] != UNLABELED) * (n + 1)
    rank = score * n_classes + (n_classes - 1 - group_class)  # unique within a voxel
    voxel_starts = np.flatnonzero(np.r_[True, group_voxel[1:] != group_voxel[:-1]])
    per_voxel = np.diff(np.r_[voxel_starts, len(groups)])
    best = np.flatnonzero(rank == np.repeat(np.maximum.reduceat(rank, voxel_starts), per_voxel))
    points = np.add.reduceat(xyz[order], starts, axis=0, dtype=np.float64)[best] \
        / counts[best, None]
    extra = {name: (np.add.reduceat(values[order], starts)[best] / counts[best]
                    ).astype(values.dtype)
             for name, values in cloud.extra.items()
             if values.ndim == 1 and np.issubdtype(values.dtype, np.floating)}
    label = None if cloud.label is None else classes[group_class[best]].astype(np.uint16)
    return LabelledCloud(points, label, extra)


def path_distance_xy(points_xy: np.ndarray, path_xy: np.ndarray, step: float = 0.25) -> np.ndarray:
    """Horizontal distance of points to the polyline through ``path_xy`` (within step / 2)."""
    path_xy = np.asarray(path_xy, float).reshape(-1, 2)
    if len(path_xy) == 0:
        return np.full(len(points_xy), np.inf)
    samples = [path_xy[:1]]
    for a, b in zip(path_xy[:-1], path_xy[1:]):
        k = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        samples.append(a + (b - a) * (np.arange(1, k + 1)[:, None] / k))
    dist, _ = cKDTree(np.concatenate(samples)).query(points_xy, workers=1)
    return dist


def remove_dynamic(cloud: LabelledCloud, dynamic_ids: np.ndarray,
                   path_xy: np.ndarray | None = None, corridor: float | None = None
                   ) -> LabelledCloud:
    """Drop points of dynamic classes; with ``corridor``, only within that distance of the path.

    The corridor keeps parked cars (the paper's KITTI maps): a car beside the road is as static
    as a wall for the minutes of a recording, and it is in the camera image too.
    """
    if cloud.label is None or len(cloud) == 0 or len(dynamic_ids) == 0:
        return cloud
    dynamic = np.isin(cloud.label, dynamic_ids)
    if not dynamic.any():
        return cloud
    if corridor is not None:
        if path_xy is None:
            raise ValueError("dynamic-class removal in a corridor needs the vehicle path")
        idx = np.flatnonzero(dynamic)
        near = path_distance_xy(cloud.xyz[idx, :2], path_xy) <= corridor
        dynamic[idx[~near]] = False
    return cloud.select(~dynamic)


def crop_radius(cloud: LabelledCloud, center: np.ndarray, radius: float) -> LabelledCloud:
    """Points within ``radius`` of ``center``, measured horizontally (x, y).

    Horizontal, so a crop around a camera keeps whole building facades and trees instead of
    cutting their tops off where a sphere would.
    """
    c = np.asarray(center, float).reshape(-1)[:2]
    d = cloud.xyz[:, :2] - c
    keep = np.einsum("ij,ij->i", d, d) <= radius * radius
    return cloud if keep.all() else cloud.select(keep)


def apply_rigid(xyz: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``xyz @ R.T + t`` computed column by column.

    A (N, 3) x (3, 3) product goes through BLAS, whose threads spin against the other processes
    on a shared 2-core machine: measured 110 ms for 170k points, against 1.5 ms this way.
    """
    r, t = matrix[:3, :3], matrix[:3, 3]
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out = np.empty((len(xyz), 3))
    for k in range(3):
        out[:, k] = x * r[k, 0] + y * r[k, 1] + z * r[k, 2] + t[k]
    return out


def transform(cloud: LabelledCloud, matrix: np.ndarray) -> LabelledCloud:
    """The cloud with its points moved by a 4x4 rigid transform (labels and extras kept)."""
    return LabelledCloud(apply_rigid(cloud.xyz, matrix), cloud.label, cloud.extra)


def concatenate(clouds: list[LabelledCloud]) -> LabelledCloud:
    """One cloud from several; if any part has labels, parts without get ``unlabeled`` (0).
    Extra fields every part has (a map's intensity) are kept; the others are dropped."""
    if not clouds:
        return LabelledCloud(np.zeros((0, 3)), np.zeros(0, np.uint16))
    xyz = np.concatenate([c.xyz for c in clouds])
    common = [k for k in clouds[0].extra if all(k in c.extra for c in clouds[1:])]
    extra = {k: np.concatenate([c.extra[k] for c in clouds]) for k in common}
    if all(c.label is None for c in clouds):
        return LabelledCloud(xyz, None, extra)
    label = np.concatenate([c.label if c.label is not None
                            else np.full(len(c), UNLABELED, np.uint16) for c in clouds])
    return LabelledCloud(xyz, label.astype(np.uint16), extra)
