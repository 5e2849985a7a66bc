"""A lidar point labeller without a network: geometry -> SemanticKITTI ids, by a small forest.

A roadside operator with an Ouster or a Livox has no trained lidar network for it, and the map
only needs the classes the calibration compares (road, sidewalk, terrain, building, fence,
vegetation, trunk, pole, traffic sign, car). :func:`label_scan` labels any scan of a roughly
level sensor (z up, sensor at the origin) in these steps:

1. **Ground level** (numpy): the median of the lowest points of 2 m cells around the sensor, so
   no mount height is assumed.
2. **Ground points**: Patchwork++ (``pypatchworkpp``), on the scan shifted so that the estimated
   ground lies ``patchwork_sensor_height`` below the origin (one Patchwork++ instance serves every
   scan and every mount height).
3. **Height above ground** of every point: a grid of the ground points' mean height, empty cells
   filled from the nearest filled cell.
4. **Kerb rules** on the ground points: a fine grid of ground heights; cells with a step to a
   neighbour above ``kerb_step`` are kerbs; the kerb-free region connected to the sensor's own
   ground (with ``road_gap``, also across the gaps between a sparse lidar's rings) is road,
   ground clearly above the nearest road is sidewalk, rough ground terrain. Their guess is one
   of the classifier's features, not the answer.
5. **Voxel features** (:mod:`~semcal_ros.segmentation.point_features`): local covariance at two
   scales (linearity, planarity, scattering, verticality), the column and object each voxel
   belongs to, kerb steps, height above the ground, range: metres and shapes, no ring count,
   no intensity.
6. **A random forest** (:mod:`~semcal_ros.segmentation.forest`, arrays shipped in
   ``segmentation/data/point_labeller.npz``, trained by ``semcal_tools/train_point_labeller.py``
   on synthetic scans of eight simulated lidars and one SemanticKITTI scan) gives each voxel its
   class shares; they are averaged over the voxel's ``smoothing_neighbours`` nearest voxels,
   and every point takes its voxel's most likely class. With ``ground_smoothing``, on the
   ground from ``ground_smoothing_from`` metres on, paved (road, sidewalk) or terrain is
   decided over ``ground_smoothing`` metres around the voxel instead: there a sparse lidar's
   nearest voxels lie on its own ring, and ring by ring the forest alternated road and
   terrain (bands across PJLab's road); road or sidewalk stays the voxel's own call. Both are
   off by default (``SPARSE_LIDAR`` has them on; docs/segmentation.md says why).

Rules alone (this module until issue 33) called facades vegetation on an unseen lidar and found
30 % of KITTI's poles; shapes at several scales, weighed by trees trained on exact labels of
many lidars, are what tells them apart (docs/segmentation.md has the figures).
Points nearer than ``min_range``, farther than ``max_range`` or not finite stay 0 (unlabeled).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from semcal_ros.engine.cloud import finite_rows
from semcal_ros.engine.labels import KITTI_ID
from semcal_ros.segmentation.forest import Forest, smoothed_best
from semcal_ros.segmentation.point_features import FEATURE_NAMES, VoxelFeatures, voxel_features

ROAD, SIDEWALK, TERRAIN = KITTI_ID["road"], KITTI_ID["sidewalk"], KITTI_ID["terrain"]
BUILDING, VEGETATION, TRUNK = KITTI_ID["building"], KITTI_ID["vegetation"], KITTI_ID["trunk"]
POLE, SIGN, CAR = KITTI_ID["pole"], KITTI_ID["traffic-sign"], KITTI_ID["car"]
FENCE = KITTI_ID["fence"]
#: What a sparse lidar (rings 1 deg apart or more near the ground, e.g. PJLab's) is labelled
#: with: the road across ring gaps and paved-or-terrain over 2 m of ground (issue 41;
#: ``config/cloud_segmenter_sparse.yaml`` holds the same for the node and the CLI).
SPARSE_LIDAR = {"road_gap": 3.0, "ground_smoothing": 2.0}
#: The model file shipped with the package.
MODEL_FILE = Path(__file__).with_name("data") / "point_labeller.npz"


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
    # --- kerb rules (a feature of the classifier) ---
    ground_cell: float = 0.3  # grid on which kerbs are found (a kerb is ~0.1-0.15 m high)
    kerb_step: float = 0.06  # height step between neighbouring cells that separates road and kerb
    road_seed_radius: float = 8.0  # ground cells this near the sensor seed the road (vehicle lidar)
    road_reach: float = 4.0  # unconnected ground this near a road cell and level with it is road
    road_level_tolerance: float = 0.05  # "level with the road": height difference below this
    terrain_roughness: float = 0.035  # ground cells whose height spread exceeds it are terrain
    road_gap: float = 0.0  # road continues across an empty radial gap this long (sparse rings;
    #                        3 m for a lidar whose rings lie 1 deg apart or more: issue 41)
    road_gap_level: float = 0.03  # ... to ground level with it within this
    road_gap_grade: float = 0.02  # ... plus this x the gap's length (a road's grade)
    # --- classifier ---
    smoothing_neighbours: int = 10  # class shares averaged over this many nearest voxels (<= 10)
    ground_smoothing: float = 0.0  # paved or terrain: decided over this radius of ground (m;
    #                                2 m for a sparse lidar: issue 41)
    ground_smoothing_from: float = 15.0  # ... this far from the sensor and beyond (sparse rings)
    min_share: float = 0.0  # voxels whose best class share is below this stay unlabeled

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"parameter 'geometric.{name}': {value} must be finite and >= 0")
        for name in ("level_cell", "height_cell", "ground_cell", "max_range"):
            if getattr(self, name) <= 0:
                raise ValueError(f"parameter 'geometric.{name}' must be > 0")
        if self.smoothing_neighbours > 10 or int(self.smoothing_neighbours) != self.smoothing_neighbours:
            raise ValueError("parameter 'geometric.smoothing_neighbours' must be an integer "
                             "in 0..10")
        if self.min_share > 1:
            raise ValueError("parameter 'geometric.min_share' must be in 0..1")


def params_from_file(path: str | Path | None) -> GeometricParams:
    """The labeller's parameters: the defaults, with the ``geometric`` group of a
    ``cloud_segmenter`` params file over them (None: the defaults). Unknown keys and bad values
    are ValueErrors naming them."""
    params = GeometricParams()
    if path is None:
        return params
    from semcal_ros.engine.config import apply_flat, load_node_group

    return apply_flat(params, load_node_group(path, "cloud_segmenter", "geometric"))


@functools.lru_cache(maxsize=2)
def load_model(path: str = str(MODEL_FILE)) -> Forest:
    """The point labeller's forest (read once per process)."""
    return Forest.load(path, FEATURE_NAMES)


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
@nb.njit(cache=True, nogil=True)
def _kerb_steps(zmean, kerb_step):  # pragma: no cover - numba
    """Kerbs: occupied cells (height not NaN) with a height step above ``kerb_step`` to an
    occupied 4-neighbour (the grid wraps at its edges, as ``np.roll`` did; its edge rows are
    empty by construction)."""
    n0, n1 = zmean.shape
    step = np.zeros((n0, n1), np.bool_)
    for i in range(n0):
        for j in range(n1):
            z = zmean[i, j]
            if np.isnan(z):
                continue
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                other = zmean[(i + di) % n0, (j + dj) % n1]
                if not np.isnan(other) and abs(z - other) > kerb_step:
                    step[i, j] = True
                    break
    return step


def _free_components(zmean: np.ndarray, free: np.ndarray, kerb_step: float
                     ) -> tuple[np.ndarray, int]:
    """(labels 1..n of the kerb-free cells' components in row-major order of their first cell,
    0 elsewhere; n). Cells join their free 8-neighbours, a diagonal one only when level with it
    within ``kerb_step``: a ring that crosses a kerb at a slant steps diagonally from road to
    sidewalk, a step the 4-neighbour kerb test does not see (joined over 8 neighbours without
    this test, such a ring made the sidewalk road)."""
    n0, n1 = free.shape
    cell = np.arange(n0 * n1).reshape(n0, n1)
    z = np.where(free, zmean, np.nan)
    links = [(free[:, :-1] & free[:, 1:], cell[:, :-1], cell[:, 1:]),
             (free[:-1] & free[1:], cell[:-1], cell[1:]),
             (np.abs(z[:-1, :-1] - z[1:, 1:]) <= kerb_step, cell[:-1, :-1], cell[1:, 1:]),
             (np.abs(z[:-1, 1:] - z[1:, :-1]) <= kerb_step, cell[:-1, 1:], cell[1:, :-1])]
    a = np.concatenate([first[ok] for ok, first, _ in links])
    b = np.concatenate([second[ok] for ok, _, second in links])
    graph = csr_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n0 * n1, n0 * n1))
    _, group = connected_components(graph, directed=False)
    members = cell[free]
    found, first = np.unique(group[members], return_index=True)
    rank = np.zeros(len(found), np.int64)
    rank[np.argsort(first)] = np.arange(1, len(found) + 1)
    labels = np.zeros((n0, n1), np.int64)
    labels[free] = rank[np.searchsorted(found, group[members])]
    return labels, len(found)


@nb.njit(cache=True, nogil=True)
def _radial_bridges(zmean, free, comp, origin, cell, max_gap, tolerance,
                    grade):  # pragma: no cover - numba
    """Pairs of components of kerb-free cells that an empty radial gap joins: from each free
    cell, walk away from the sensor (at ``origin``, in cells) over empty cells, at most ``max_gap``
    cells; a free cell reached whose height differs by less than ``tolerance + grade x gap``
    (metres) is the same surface seen by the next ring. A sparse lidar's rings lie 1-2 m apart
    on the road at 15-30 m: without this each ring is a piece of its own and only the first
    ones near the sensor are road (PJLab's bands of sidewalk and terrain across the road)."""
    n0, n1 = zmean.shape
    out_a = []
    out_b = []
    for i in range(n0):
        for j in range(n1):
            if not free[i, j]:
                continue
            di, dj = i + 0.5 - origin, j + 0.5 - origin
            norm = np.sqrt(di * di + dj * dj)
            if norm < 1.0:
                continue
            di, dj = di / norm, dj / norm
            for k in range(1, max_gap + 1):
                ii = int(np.floor(i + 0.5 + di * k))
                jj = int(np.floor(j + 0.5 + dj * k))
                if ii < 0 or jj < 0 or ii >= n0 or jj >= n1:
                    break
                if np.isnan(zmean[ii, jj]):
                    continue
                if free[ii, jj] and comp[ii, jj] != comp[i, j] \
                        and abs(zmean[ii, jj] - zmean[i, j]) < tolerance + grade * k * cell:
                    out_a.append(comp[i, j])
                    out_b.append(comp[ii, jj])
                break
    return np.array(out_a, np.int64), np.array(out_b, np.int64)


def _road_components(zmean: np.ndarray, free: np.ndarray, seed: np.ndarray,
                     params: GeometricParams, grid: _Grid) -> np.ndarray:
    """The kerb-free cells connected to the road seed: 8-neighbours, and with ``road_gap``
    across empty radial gaps (:func:`_radial_bridges`; diagonal neighbours then join only when
    level, :func:`_free_components`). Without it, the labeller's pieces as before issue 41."""
    gap = int(np.floor(params.road_gap / grid.cell))
    if gap > 0:
        comp, ncomp = _free_components(zmean, free, params.kerb_step)
    else:
        comp, ncomp = ndimage.label(free, structure=np.ones((3, 3)))
    if not ncomp or not seed.any():
        return np.zeros_like(free)
    votes = np.bincount(comp[seed], minlength=ncomp + 1)
    votes[0] = 0
    start = int(np.argmax(votes))
    if gap > 0:
        a, b = _radial_bridges(zmean, free, comp, grid.radius / grid.cell, grid.cell, gap,
                               params.road_gap_level, params.road_gap_grade)
        if len(a):
            graph = csr_matrix((np.ones(len(a)), (a, b)), shape=(ncomp + 1, ncomp + 1))
            _, group = connected_components(graph, directed=False)
            return (comp > 0) & (group[comp] == group[start])
    return comp == start


def _ground_classes(xyz: np.ndarray, ground_level: float, params: GeometricParams) -> np.ndarray:
    """Road / sidewalk / terrain for ground points (see the module doc, step 4)."""
    radius = float(min(params.max_range, np.abs(xyz[:, :2]).max() + params.ground_cell))
    grid = _Grid(params.ground_cell, radius)
    idx = grid.flat(xyz[:, :2])
    zmean, count = grid.mean(idx, xyz[:, 2])
    z2, _ = grid.mean(idx, xyz[:, 2] ** 2)
    spread = np.sqrt(np.maximum(z2 - zmean ** 2, 0.0))
    occupied = count > 0
    step = _kerb_steps(zmean, params.kerb_step)
    free = occupied & ~step
    centre = (np.arange(grid.n) + 0.5) * grid.cell - radius
    cx, cy = np.meshgrid(centre, centre, indexing="ij")
    seed = free & (np.hypot(cx, cy) < params.road_seed_radius) \
        & (np.abs(zmean - ground_level) < 3 * params.kerb_step)
    road = _road_components(zmean, free, seed, params, grid)
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



# --- entry ------------------------------------------------------------------------------------
#: Kerb-rule class -> feature value (0 road, 1 sidewalk, 2 terrain).
_RULE_CODE = {ROAD: 0, SIDEWALK: 1, TERRAIN: 2}


def scan_features(xyz: np.ndarray, intensity: np.ndarray | None = None,
                  params: GeometricParams | None = None) -> tuple[np.ndarray, VoxelFeatures]:
    """(indices of the scan points that are labelled, their voxels' features): steps 1-5 of
    the module doc. The training script calls this too, so model and labeller see the same
    numbers. ``ValueError`` (one line) for a scan that is not (N, 3), is empty, has no usable
    point, or whose intensity length differs."""
    params = params or GeometricParams()
    xyz, intensity = _validated(xyz, intensity)
    finite = finite_rows(xyz)
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

    rule = np.full(len(pts), -1, np.int8)
    if ground.any():
        ground_ids = _ground_classes(pts[ground], level, params)
        lut = np.zeros(int(ground_ids.max()) + 1, np.int8)
        for kitti_id, code in _RULE_CODE.items():
            if kitti_id < len(lut):
                lut[kitti_id] = code
        rule[ground] = lut[ground_ids]
    return index, voxel_features(pts, ground, height, rule)


def _area_smoothed(shares: np.ndarray, xy: np.ndarray, radius: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(best class column, its share) of ground voxels after averaging their class shares over
    the ground voxels in a square of about 2 x ``radius`` metres around each: an area in metres,
    where the nearest voxels are a sparse lidar's own ring (a ring apart is 1-3 m at 20-40 m)."""
    cell = 0.5
    half = max(1, int(round(radius / cell)))
    ij = np.floor(xy / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    shape = tuple(ij.max(axis=0) + 1)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    size = 2 * half + 1
    total = np.zeros((shares.shape[1], *shape), np.float64)
    for c in range(shares.shape[1]):
        grid = np.bincount(flat, shares[:, c], minlength=shape[0] * shape[1]).reshape(shape)
        total[c] = ndimage.uniform_filter(grid, size=size, mode="constant")
    counts = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape).astype(np.float64)
    counts = ndimage.uniform_filter(counts, size=size, mode="constant")
    mean = total.reshape(shares.shape[1], -1)[:, flat] / np.maximum(counts.ravel()[flat], 1e-12)
    best = mean.argmax(axis=0)
    return best, mean[best, np.arange(len(best))].astype(np.float32)


def _paved_or_terrain(best: np.ndarray, top: np.ndarray, shares: np.ndarray,
                      classes: np.ndarray, feats: VoxelFeatures, pts: np.ndarray,
                      params: GeometricParams) -> tuple[np.ndarray, np.ndarray]:
    """(best, top) with the ground voxels from ``ground_smoothing_from`` on whose best class is
    road, sidewalk or terrain decided paved or terrain over their area (:func:`_area_smoothed`)
    and road or sidewalk by their own neighbours, as before. ``pts``: the labelled points."""
    col = {int(c): i for i, c in enumerate(classes)}
    road, side, terr = col[ROAD], col[SIDEWALK], col[TERRAIN]
    g = feats.ground & np.isin(best, (road, side, terr)) \
        & (feats.values[:, 2] >= params.ground_smoothing_from)
    if not g.any():
        return best, top
    count = np.bincount(feats.inverse).astype(np.float64)
    xy = np.stack([np.bincount(feats.inverse, pts[:, a]) / count for a in (0, 1)], axis=1)
    two = np.stack([shares[g, road] + shares[g, side], shares[g, terr]], axis=1)
    area, area_top = _area_smoothed(two, xy[g], params.ground_smoothing)
    own = np.where(shares[g, road] >= shares[g, side], road, side)
    best, top = best.copy(), top.copy()
    best[g] = np.where(area == 1, terr, np.where(np.isin(best[g], (road, side)), best[g], own))
    top[g] = area_top
    return best, top


def label_scan(xyz: np.ndarray, intensity: np.ndarray | None = None,
               params: GeometricParams | None = None, model: str | Path | None = None
               ) -> np.ndarray:
    """(N,) uint16 SemanticKITTI ids of one scan in the lidar frame (z up, sensor at origin).

    Points with NaN/inf coordinates, nearer than ``min_range`` or farther than ``max_range``
    get 0 (unlabeled), as do voxels the forest leaves to its "other" class (people, bicycles,
    clutter). ``ValueError`` (one line) for a scan that is not (N, 3), is empty, has no usable
    point, or whose intensity length differs. ``model``: another forest file (default: the
    shipped one).
    """
    params = params or GeometricParams()
    index, feats = scan_features(xyz, intensity, params)
    forest = load_model(str(model)) if model is not None else load_model()
    shares = forest.predict_proba(feats.values)
    k = min(int(params.smoothing_neighbours), feats.neighbours.shape[1])
    if k > 1:
        best, top = smoothed_best(shares, feats.neighbours, k)
    else:
        best, top = shares.argmax(axis=1), shares.max(axis=1)
    if params.ground_smoothing > 0:
        best, top = _paved_or_terrain(best, top, shares, forest.classes, feats,
                                      np.asarray(xyz, np.float64)[index], params)
    voxel_label = forest.classes[best]
    if params.min_share > 0:
        voxel_label = np.where(top >= params.min_share, voxel_label, 0)
    labels = np.zeros(len(xyz), np.uint16)
    labels[index] = voxel_label[feats.inverse]
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


#: Coarse groups of SemanticKITTI ids (issue 33's measure; issue 41's per-pattern targets).
COARSE = {
    "ground": ("road", "lane-marking", "parking", "sidewalk", "other-ground", "terrain"),
    "building": ("building", "other-structure"),
    "vegetation": ("vegetation", "trunk"),
    "pole": ("pole", "traffic-sign"),
    "vehicle": ("car", "truck", "bus", "other-vehicle", "moving-car", "moving-truck",
                "moving-bus", "moving-other-vehicle"),
}


def coarse_agreement(predicted: np.ndarray, reference: np.ndarray
                     ) -> tuple[float, dict[str, tuple[float, float, int]]]:
    """(overall, {group: (precision, recall, reference points)}) over the reference points of
    the :data:`COARSE` groups: a point agrees when its prediction is in its reference's group."""
    lut = np.zeros(65536, np.int8)
    for k, members in enumerate(COARSE.values(), start=1):
        for name in members:
            lut[KITTI_ID[name]] = k
    cp, cr = lut[np.asarray(predicted)], lut[np.asarray(reference)]
    keep = cr > 0
    groups = {}
    for k, name in enumerate(COARSE, start=1):
        both = int(((cr == k) & (cp == k)).sum())
        n_ref, n_pred = int((cr == k).sum()), int((cp == k).sum())
        groups[name] = (both / max(n_pred, 1), both / max(n_ref, 1), n_ref)
    overall = float((cp[keep] == cr[keep]).mean()) if keep.any() else float("nan")
    return overall, groups
