"""A lidar point labeller without a network: geometry (and intensity where it helps) -> SemanticKITTI ids.

A roadside operator with an Ouster or a Livox has no trained lidar network for it, and the map
only needs the classes the calibration compares (ground, building, vegetation, pole, car, ...).
Those can be told apart by shape, so :func:`label_scan` labels any scan of a roughly level sensor
(z up, sensor at the origin) in these steps:

1. **Ground level** (hand-written, numpy): the median of the lowest points of 2 m cells around the
   sensor, so no mount height is assumed.
2. **Ground points**: Patchwork++ (``pypatchworkpp``), on the scan shifted so that the estimated
   ground lies ``patchwork_sensor_height`` below the origin (one Patchwork++ instance serves every
   scan and every mount height).
3. **Height above ground** of every point (hand-written, numpy/scipy): a grid of the ground
   points' mean height, empty cells filled from the nearest filled cell.
4. **Road, sidewalk, terrain** (hand-written: no library splits ground by kerbs): a fine grid
   of ground heights; cells with a height step to a neighbour above ``kerb_step`` are kerbs; the
   kerb-free region connected to the sensor's own ground is road (the vehicle stands on it),
   ground standing clearly above the nearest road is sidewalk, rough ground is terrain.
5. **Objects**: the other points in 0.2 m voxels; Open3D gives each voxel its neighbourhood
   covariance (eigen features: linear, planar, scattered; the normal) and clusters the voxels
   (DBSCAN). Hand-written rules on cluster shape (footprint, height span, how much of it is
   planar) call a cluster car, pole (traffic-sign for a plate on it), trunk (a thick column) or a
   mixed structure, whose voxels become building (planar, vertical) or vegetation (scattered)
   by a neighbourhood vote. Nothing library-made classifies clusters by such rules.

What it cannot tell (tiny isolated clusters, returns below the ground) stays 0 (unlabeled).
The rules use metres and shapes, not a sensor's ring count, so they serve any spinning or
solid-state lidar; intensity is only an optional tie-breaker (``car_max_intensity``).
"""

from __future__ import annotations

import contextlib
import os
import threading
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from semcal_ros.engine.labels import KITTI_ID

ROAD, SIDEWALK, TERRAIN = KITTI_ID["road"], KITTI_ID["sidewalk"], KITTI_ID["terrain"]
BUILDING, VEGETATION, TRUNK = KITTI_ID["building"], KITTI_ID["vegetation"], KITTI_ID["trunk"]
POLE, SIGN, CAR = KITTI_ID["pole"], KITTI_ID["traffic-sign"], KITTI_ID["car"]


@dataclass
class GeometricParams:
    """Every threshold of :func:`label_scan`, with what it buys (metres unless said)."""

    # --- scan ---
    min_range: float = 1.0  # points nearer the sensor are the vehicle / mast itself: unlabeled
    max_range: float = 100.0  # points farther are too sparse to classify: unlabeled
    # --- ground level and Patchwork++ ---
    level_cell: float = 2.0  # cell of the ground-level estimate (lowest point per cell)
    level_min_range: float = 3.0  # ... taken from cells this far from the sensor
    level_max_range: float = 25.0  # ... and not farther (far cells are sparse and sloped)
    patchwork_sensor_height: float = 1.7  # Patchwork++ sees the ground this far below its origin
    patchwork_max_range: float = 80.0  # Patchwork++ ground search radius
    # --- height above ground ---
    height_cell: float = 1.0  # grid of the ground height (finer: follows slopes, more holes)
    # --- road / sidewalk / terrain ---
    ground_cell: float = 0.3  # grid on which kerbs are found (a kerb is ~0.1-0.15 m high)
    kerb_step: float = 0.06  # height step between neighbouring cells that separates road and kerb
    road_seed_radius: float = 8.0  # ground cells this near the sensor seed the road (vehicle lidar)
    road_reach: float = 4.0  # unconnected ground this near a road cell and level with it is road
    road_level_tolerance: float = 0.05  # "level with the road": height difference below this
    terrain_roughness: float = 0.035  # ground cells whose height spread exceeds it are terrain
    # --- objects ---
    voxel: float = 0.2  # object voxel size: features and clusters are computed per voxel
    feature_radius: float = 1.5  # farthest neighbour of a voxel's covariance (sparse far walls need ~1.5)
    feature_max_nn: int = 16  # nearest neighbours used (dense areas stay local; speed)
    cluster_eps: float = 0.5  # DBSCAN radius: voxels nearer than this belong to one object
    cluster_min_voxels: int = 3  # DBSCAN core size; smaller groups are noise (unlabeled)
    min_object_points: int = 8  # clusters with fewer points stay unlabeled
    # car: a compact box standing on the ground, nothing above it
    car_min_length: float = 1.0  # footprint's long side (a car seen end-on shows ~1.5 m)
    car_max_length: float = 6.0  # longer is a wall, a hedge or a bus
    car_max_width: float = 2.6  # footprint short side: wider is no car
    car_min_top: float = 0.8  # top of the cluster above ground
    car_max_top: float = 2.1  # vans up to ~2.1 m; higher is a hedge or a wall
    car_max_bottom: float = 0.6  # lowest point above ground (a car touches the ground)
    car_max_scatter: float = 0.12  # mean scattering of its voxels (cars are smooth; bushes not)
    car_max_intensity: float = 1.0e9  # median intensity at most this (off by default)
    # pole / trunk: a thin vertical column
    pole_max_width: float = 0.9  # footprint's long side of a pole (with a sign: up to ~0.9 m)
    pole_min_height: float = 1.5  # vertical span
    trunk_min_thickness: float = 0.25  # a column this thick (slice spread) is a trunk, not a pole
    sign_min_spread: float = 0.35  # a slice of a pole this wide is a sign plate on it
    # building vs vegetation, per voxel
    wall_min_planarity: float = 0.45  # planar ...
    wall_max_normal_z: float = 0.35  # ... with a horizontal normal (a vertical surface): building
    vote_cell: float = 0.6  # cube of the majority vote that smooths building/vegetation

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"parameter 'geometric.{name}': {value} must be finite and >= 0")
        for name in ("level_cell", "height_cell", "ground_cell", "voxel", "feature_radius",
                     "cluster_eps", "vote_cell", "max_range"):
            if getattr(self, name) <= 0:
                raise ValueError(f"parameter 'geometric.{name}' must be > 0")


# --- Patchwork++ ------------------------------------------------------------------------------
_STDOUT_LOCK = threading.Lock()


@contextlib.contextmanager
def _quiet_stdout():
    """Patchwork++'s constructor prints a line on the C stdout; keep command output clean."""
    with _STDOUT_LOCK:
        try:
            fd = os.dup(1)
        except OSError:
            yield
            return
        try:
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 1)
                yield
        finally:
            os.dup2(fd, 1)
            os.close(fd)


def _patchwork(params: GeometricParams):
    """A fresh Patchwork++ per scan (0.02 ms): an instance adapts its thresholds to the scans it
    has seen, and the labels of a scan must not depend on which scans came before it."""
    import pypatchworkpp

    pw = pypatchworkpp.Parameters()
    pw.sensor_height = params.patchwork_sensor_height
    pw.max_range = params.patchwork_max_range
    pw.min_range = 0.5
    pw.verbose = False
    with _quiet_stdout():
        return pypatchworkpp.patchworkpp(pw)


# --- helpers ----------------------------------------------------------------------------------
def _validated(xyz: np.ndarray, intensity: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"scan must be an (N, 3) array of x, y, z, got shape {xyz.shape}")
    if len(xyz) == 0:
        raise ValueError("scan is empty (0 points)")
    if intensity is None:
        inten = np.zeros(len(xyz), np.float64)
    else:
        inten = np.asarray(intensity, np.float64).reshape(-1)
        if len(inten) != len(xyz):
            raise ValueError(f"intensity has {len(inten)} values for {len(xyz)} points")
        inten = np.where(np.isfinite(inten), inten, 0.0)
    return xyz, inten


class _Grid:
    """A square 2-D grid around the sensor; ``flat(xy)`` gives each point's cell index."""

    def __init__(self, cell: float, radius: float) -> None:
        self.cell = cell
        self.n = int(np.ceil(2 * radius / cell)) + 1
        self.radius = radius

    def ij(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((xy + self.radius) / self.cell).astype(np.int64)
        return np.clip(ij, 0, self.n - 1)

    def flat(self, xy: np.ndarray) -> np.ndarray:
        ij = self.ij(xy)
        return ij[:, 0] * self.n + ij[:, 1]

    def mean(self, idx: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        count = np.bincount(idx, minlength=self.n * self.n).astype(np.float64)
        total = np.bincount(idx, values, minlength=self.n * self.n)
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        return mean.reshape(self.n, self.n), count.reshape(self.n, self.n)


def _fill_nearest(grid: np.ndarray) -> np.ndarray:
    """NaN cells take the value of the nearest filled cell."""
    empty = np.isnan(grid)
    if empty.all():
        return np.zeros_like(grid)
    if not empty.any():
        return grid
    _, (ii, jj) = ndimage.distance_transform_edt(empty, return_indices=True)
    return grid[ii, jj]


def estimate_ground_level(xyz: np.ndarray, params: GeometricParams) -> float:
    """Height of the ground around the sensor: median over nearby cells of each cell's lowest
    point (walls and cars stand on the ground, so a cell's lowest return is ground or near it)."""
    rng = np.hypot(xyz[:, 0], xyz[:, 1])
    near = (rng > params.level_min_range) & (rng < params.level_max_range)
    if near.sum() < 50:
        near = rng > 0
    grid = _Grid(params.level_cell, params.level_max_range)
    idx = grid.flat(xyz[near, :2])
    lowest = np.full(grid.n * grid.n, np.inf)
    np.minimum.at(lowest, idx, xyz[near, 2])
    lowest = lowest[np.isfinite(lowest)]
    return float(np.median(lowest))


# --- ground classes ---------------------------------------------------------------------------
def _ground_classes(xyz: np.ndarray, ground_level: float, params: GeometricParams) -> np.ndarray:
    """Road / sidewalk / terrain for ground points (see the module doc, step 4)."""
    radius = float(min(params.max_range, np.abs(xyz[:, :2]).max() + params.ground_cell))
    grid = _Grid(params.ground_cell, radius)
    idx = grid.flat(xyz[:, :2])
    zmean, count = grid.mean(idx, xyz[:, 2])
    z2, _ = grid.mean(idx, xyz[:, 2] ** 2)
    spread = np.sqrt(np.maximum(z2 - zmean ** 2, 0.0))
    occupied = count > 0
    # kerbs: a step to any 4-neighbour
    step = np.zeros_like(occupied)
    for axis in (0, 1):
        for shift in (1, -1):
            other = np.roll(zmean, shift, axis=axis)
            both = occupied & ~np.isnan(other)
            step |= both & (np.abs(np.nan_to_num(zmean - other)) > params.kerb_step)
    free = occupied & ~step
    comp, ncomp = ndimage.label(free, structure=np.ones((3, 3)))
    centre = (np.arange(grid.n) + 0.5) * grid.cell - radius
    cx, cy = np.meshgrid(centre, centre, indexing="ij")
    seed = free & (np.hypot(cx, cy) < params.road_seed_radius) \
        & (np.abs(zmean - ground_level) < 3 * params.kerb_step)
    road = np.zeros_like(occupied)
    if ncomp and seed.any():
        votes = np.bincount(comp[seed], minlength=ncomp + 1)
        votes[0] = 0
        road = comp == int(np.argmax(votes))
    # ground not connected to the road: level with the nearest road nearby -> road,
    # above it -> sidewalk; rough -> terrain
    label = np.full(occupied.shape, SIDEWALK, np.uint16)
    if road.any():
        dist, (ii, jj) = ndimage.distance_transform_edt(~road, return_indices=True)
        road_z = zmean[ii, jj]
        near = dist * grid.cell < params.road_reach
        level = np.abs(zmean - road_z) < params.road_level_tolerance
        road_like = road | (occupied & ~step & near & level)
        label[road_like] = ROAD
    label[occupied & (spread > params.terrain_roughness) & (label != ROAD)] = TERRAIN
    return label.ravel()[idx]


# --- objects ----------------------------------------------------------------------------------
def _voxelize(xyz: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(voxel of each point, voxel centroids, points per voxel)."""
    key = np.floor(xyz / size).astype(np.int64)
    key -= key.min(axis=0)
    dims = key.max(axis=0) + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    _, inverse, count = np.unique(flat, return_inverse=True, return_counts=True)
    centroid = np.stack([np.bincount(inverse, xyz[:, i]) / count for i in range(3)], axis=1)
    return inverse, centroid, count


def _eigen_features(centroid: np.ndarray, params: GeometricParams):
    """(linearity, planarity, scattering, |normal z|, |main axis z|) per voxel, and the
    Open3D cloud (reused for clustering)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centroid))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(
        params.feature_radius, params.feature_max_nn))
    cov = np.asarray(cloud.covariances)
    values, vectors = np.linalg.eigh(cov)  # ascending
    values = np.maximum(values, 1e-12)
    l3, l2, l1 = values[:, 0], values[:, 1], values[:, 2]
    linear = (l1 - l2) / l1
    planar = (l2 - l3) / l1
    scatter = l3 / l1
    normal_z = np.abs(vectors[:, 2, 0])
    axis_z = np.abs(vectors[:, 2, 2])
    return linear, planar, scatter, normal_z, axis_z, cloud


def _footprint(xy: np.ndarray) -> tuple[float, float]:
    """(long, short) side of a cluster's footprint: 4 sigma along its principal axes (robust
    to stray points, ~ the extent for a uniformly covered rectangle's 3.5 sigma)."""
    if len(xy) < 3:
        return 0.0, 0.0
    cov = np.cov((xy - xy.mean(axis=0)).T)
    ev = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 0.0))
    return float(3.5 * ev[1]), float(3.5 * ev[0])


def _slice_spread(xyz: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Horizontal spread (max distance from the slice's mean) of 0.3 m height slices."""
    out = []
    for lo in np.arange(height.min(), height.max(), 0.3):
        sel = (height >= lo) & (height < lo + 0.3)
        if sel.sum() >= 3:
            xy = xyz[sel, :2]
            out.append(float(np.hypot(*(xy - xy.mean(axis=0)).T).max()))
    return np.array(out) if out else np.zeros(1)


def _object_classes(xyz: np.ndarray, height: np.ndarray, intensity: np.ndarray,
                    params: GeometricParams) -> np.ndarray:
    """Labels of the non-ground points (see the module doc, step 5)."""
    labels = np.zeros(len(xyz), np.uint16)
    if len(xyz) < params.cluster_min_voxels:
        return labels
    inverse, centroid, count = _voxelize(xyz, params.voxel)
    linear, planar, scatter, normal_z, axis_z, cloud = _eigen_features(centroid, params)
    cluster = np.asarray(cloud.cluster_dbscan(params.cluster_eps, params.cluster_min_voxels))
    point_cluster = cluster[inverse]
    voxel_height = np.bincount(inverse, height) / count

    # per voxel: building where planar and vertical, vegetation elsewhere; majority vote
    wall = (planar > params.wall_min_planarity) & (normal_z < params.wall_max_normal_z)
    coarse, _, _ = _voxelize(centroid, params.vote_cell)
    weight = count.astype(np.float64)
    wall_share = (np.bincount(coarse, weight * wall) / np.bincount(coarse, weight))[coarse]
    voxel_label = np.where(wall_share > 0.5, BUILDING, VEGETATION).astype(np.uint16)
    labels[:] = voxel_label[inverse]

    order = np.argsort(point_cluster, kind="stable")
    bounds = np.searchsorted(point_cluster[order], np.arange(cluster.max() + 2) - 1)
    labels[point_cluster < 0] = 0
    for c in range(cluster.max() + 1):
        members = order[bounds[c + 1]:bounds[c + 2]] if c + 2 < len(bounds) else \
            order[bounds[c + 1]:]
        if len(members) < params.min_object_points:
            labels[members] = 0
            continue
        p = xyz[members]
        h = height[members]
        length, width = _footprint(p[:, :2])
        top, bottom = float(np.percentile(h, 98)), float(np.percentile(h, 2))
        vox = np.unique(inverse[members])
        mean_scatter = float(np.average(scatter[vox], weights=count[vox]))
        if (params.car_min_length <= length <= params.car_max_length and width <= params.car_max_width
                and params.car_min_top <= top <= params.car_max_top
                and bottom <= params.car_max_bottom and mean_scatter <= params.car_max_scatter
                and np.median(intensity[members]) <= params.car_max_intensity):
            labels[members] = CAR
            continue
        if length <= params.pole_max_width and top - bottom >= params.pole_min_height:
            spread = _slice_spread(p, h)
            column = float(np.median(spread))
            if column >= params.trunk_min_thickness:
                labels[members] = TRUNK
            else:
                labels[members] = POLE
                # sign plates: slices much wider than the column
                for lo in np.arange(bottom, top, 0.3):
                    sel = (h >= lo) & (h < lo + 0.3)
                    if sel.sum() >= 3:
                        xy = p[sel, :2]
                        if np.hypot(*(xy - xy.mean(axis=0)).T).max() > params.sign_min_spread:
                            labels[members[sel]] = SIGN
    del voxel_height, linear, axis_z
    return labels


# --- entry ------------------------------------------------------------------------------------
def label_scan(xyz: np.ndarray, intensity: np.ndarray | None = None,
               params: GeometricParams | None = None) -> np.ndarray:
    """(N,) uint16 SemanticKITTI ids of one scan in the lidar frame (z up, sensor at origin).

    Points with NaN/inf coordinates, nearer than ``min_range`` or farther than ``max_range``
    get 0 (unlabeled), as do points the rules cannot tell. ``ValueError`` (one line) for a scan
    that is not (N, 3), is empty, has no usable point, or whose intensity length differs.
    """
    params = params or GeometricParams()
    xyz, intensity = _validated(xyz, intensity)
    labels = np.zeros(len(xyz), np.uint16)
    finite = np.isfinite(xyz).all(axis=1)
    pts = np.where(finite[:, None], xyz, 0.0).astype(np.float64)
    rng = np.linalg.norm(pts, axis=1)
    use = finite & (rng >= params.min_range) & (rng <= params.max_range)
    if use.sum() < 100:
        raise ValueError(f"scan has {int(use.sum())} usable points (finite, {params.min_range}-"
                         f"{params.max_range} m from the sensor) of {len(xyz)}: too few to label")
    index = np.flatnonzero(use)
    pts, inten = pts[use], intensity[use]

    level = estimate_ground_level(pts, params)
    shifted = pts.copy()
    shifted[:, 2] -= level + params.patchwork_sensor_height
    pw = _patchwork(params)
    pw.estimateGround(np.c_[shifted, inten])
    ground_idx = np.asarray(pw.getGroundIndices(), np.int64)
    ground = np.zeros(len(pts), bool)
    ground[ground_idx] = True

    grid = _Grid(params.height_cell, float(np.abs(pts[:, :2]).max()) + params.height_cell)
    cell = grid.flat(pts[:, :2])
    gmean, _ = grid.mean(cell[ground], pts[ground, 2]) if ground.any() else \
        (np.full((grid.n, grid.n), level), None)
    surface = _fill_nearest(gmean).ravel()
    height = pts[:, 2] - surface[cell]

    sub = np.zeros(len(pts), np.uint16)
    if ground.any():
        sub[ground] = _ground_classes(pts[ground], level, params)
    objects = ~ground
    sub[objects] = _object_classes(pts[objects], height[objects], inten[objects], params)
    labels[index] = sub
    return labels


# --- agreement with reference labels (benchmark and tests) ------------------------------------
#: Rows of the agreement table, in the engine's aligned (Cityscapes) classes.
TABLE_CLASSES = ("road", "sidewalk", "terrain", "building", "fence", "vegetation", "pole",
                 "traffic sign", "car")
#: The ground group: any ground class for any ground truth counts as "ground".
GROUND_CLASSES = ("road", "sidewalk", "terrain")


@dataclass(frozen=True)
class PointAgreement:
    """Per-class precision/recall of predicted vs reference point labels, in aligned classes."""

    overall: float  # share of reference points (valid aligned class) whose prediction agrees
    points: int
    per_class: dict  # name -> (precision, recall, reference points, predicted points)

    def table(self) -> str:
        lines = ["| class | reference points | precision | recall |", "|---|---|---|---|"]
        for name, (prec, rec, n_ref, _) in self.per_class.items():
            lines.append(f"| {name} | {n_ref} | {100 * prec:.1f} % | {100 * rec:.1f} % |")
        lines.append(f"| **overall** | {self.points} | | **{100 * self.overall:.1f} %** |")
        return "\n".join(lines)


def point_agreement(predicted: np.ndarray, reference: np.ndarray, mapping=None,
                    classes: tuple[str, ...] = TABLE_CLASSES) -> PointAgreement:
    """Compare SemanticKITTI ids in the engine's aligned classes (``mapping``: a
    :class:`~semcal_ros.engine.labels.LabelMapping`, default: the engine's alignment with every class
    kept, cars included). Points whose reference has no aligned class (unlabeled, outlier,
    other-object) are left out; a prediction without one (0) counts as a miss. ``"ground"``
    is added: any ground class predicted for any ground reference."""
    from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, LabelMapping

    mapping = mapping or LabelMapping(dynamic=())
    ref = mapping.map_lidar(reference)
    pred = mapping.map_lidar(predicted)
    keep = ref != INVALID
    ref, pred = ref[keep], pred[keep]
    per_class = {}
    ids = {}
    for name in classes:
        ids[name] = CITYSCAPES_ID[mapping.merge.get(name, name)]
    ground_ids = np.unique([ids[n] for n in GROUND_CLASSES if n in ids])
    groups = [(n, np.array([ids[n]])) for n in classes]
    groups.append(("ground", ground_ids))
    for name, members in groups:
        is_ref, is_pred = np.isin(ref, members), np.isin(pred, members)
        both = int((is_ref & is_pred).sum())
        per_class[name] = (both / max(int(is_pred.sum()), 1), both / max(int(is_ref.sum()), 1),
                           int(is_ref.sum()), int(is_pred.sum()))
    return PointAgreement(float((ref == pred).mean()) if len(ref) else float("nan"),
                          int(len(ref)), per_class)
