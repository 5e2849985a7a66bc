"""Multiway ICP of a group of neighbouring clouds (the paper's step 1, one level of the recursion).

The clouds of a group are already in the map frame, placed by the vehicle's poses; registration
finds small rigid corrections. Point-to-plane ICP runs between each pair of neighbours (and between
the first and the last, as a less certain loop edge), then Open3D's pose-graph optimisation makes
the pairwise results agree. Lidar alone cannot tell where the whole group sits in the map (only
where its members sit relative to each other), so the corrections are finally re-anchored such
that their weighted mean, taken about the group's centroid, is the identity: the group as a whole
stays where the poses put it, and independent pose errors average out level by level.

The ICP itself is ``small_gicp`` (PyPI): generalized ICP (plane-to-plane, each point with the
covariance of its neighbours) on a k-d tree, single-threaded. On one 124k-point KITTI scan pair
it took about 50 ms where Open3D's point-to-plane tensor ICP took 290 ms (one thread each,
docs/mapping.md), and on the pose-noise scene it leaves a third of the error (0.25 cm /
0.012 deg where Open3D left 0.76 cm / 0.035 deg). Each cloud has two grids: a fine one that
serves as the target (k-d tree and covariances made once, when first needed) and a coarse one,
capped in size, that serves as the source.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import small_gicp
from scipy.spatial.transform import Rotation

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.mapping.filters import apply_rigid, voxel_downsample


@dataclass
class RegistrationParams:
    """Parameters of the pairwise ICP (coarse-to-fine stages) and of the pose graph."""

    target_voxel: float = 0.6  # m, grid of a cloud as an ICP target
    source_voxel: float = 0.6  # m, grid of a cloud as an ICP source (its points move)
    max_correspondence: tuple[float, ...] = (1.2, 0.45)  # partner search distance per stage
    max_iterations: int = 30  # per stage
    converged_deg: float = 0.005  # a stage stops when an iteration turns the cloud less than
    converged_m: float = 0.0002  # this and moves it less than this (small_gicp's defaults,
    # 0.1 deg / 1 mm, stop early by a few hundredths of a degree)
    max_source_points: int = 6000  # ICP moves a random subset of the source grid (0: all)
    max_target_points: int = 15000  # a merged cloud beyond this gets a coarser target grid,
    # so the covariances of big merged clouds at high levels cost no more than a few scans'
    neighbours: int = 10  # points whose spread gives each point's covariance
    min_fitness: float = 0.2  # fraction of source points with a partner; less: edge dropped
    max_correction_m: float = 2.0  # an ICP result moving a cloud further is dropped
    max_correction_deg: float = 5.0
    loop_edges: bool = True  # add first -> last as an uncertain edge in groups of three
    edge_prune_threshold: float = 0.25

    def __post_init__(self) -> None:
        self.max_correspondence = tuple(float(v) for v in self.max_correspondence)
        if not self.max_correspondence or min(self.max_correspondence) <= 0:
            raise ValueError("max_correspondence needs one positive distance per ICP stage")
        if not self.target_voxel > 0 or not self.source_voxel > 0:
            raise ValueError("ICP voxel sizes must be positive")
        if self.neighbours < 5 or self.max_iterations < 1 or self.max_target_points < 0 \
                or self.max_source_points < 0:
            raise ValueError("neighbours must be >= 5, max_iterations >= 1 and the point "
                             "caps >= 0")


@dataclass(frozen=True)
class PairResult:
    """ICP of one edge: ``transformation`` moves source points onto the target."""

    source: int
    target: int
    transformation: np.ndarray
    information: np.ndarray
    fitness: float
    rmse: float
    accepted: bool
    reason: str = ""


@dataclass(frozen=True)
class GroupResult:
    """Corrections (4x4, map frame, applied on the left of each member) and the edges used."""

    corrections: list[np.ndarray]
    pairs: list[PairResult]


def _gicp_cloud(points: np.ndarray, center: np.ndarray, neighbours: int) -> tuple:
    cloud = small_gicp.PointCloud(points - center)
    tree = small_gicp.KdTree(cloud, 1)
    small_gicp.estimate_covariances(cloud, tree, neighbours, 1)
    return cloud, tree


@dataclass
class RegistrationCloud:
    """What ICP works on, map frame (labels do not matter for registration): voxel centroids on
    the target grid (``points``) and on the source grid (``source_points``, capped). Their
    small_gicp clouds (k-d tree, covariances) are made once, when first needed, about
    ``center`` so that georeferenced coordinates keep their precision."""

    points: np.ndarray  # (M, 3) float64 target grid
    source_points: np.ndarray  # (K, 3) float64 source grid, at most max_source_points
    center: np.ndarray  # centroid of the points, map frame
    _target: tuple | None = field(default=None, repr=False)
    _source: tuple | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    def target(self, params: RegistrationParams) -> tuple:
        """(small_gicp.PointCloud with covariances, its KdTree) of the target grid."""
        if self._target is None:
            self._target = _gicp_cloud(self.points, self.center, params.neighbours)
        return self._target

    def source(self, params: RegistrationParams) -> tuple:
        """(small_gicp.PointCloud with covariances, its KdTree) of the source grid."""
        if self._source is None:
            self._source = _gicp_cloud(self.source_points, self.center, params.neighbours)
        return self._source


def _grid(xyz: np.ndarray, voxel: float) -> np.ndarray:
    return voxel_downsample(LabelledCloud(xyz), voxel).xyz if len(xyz) else np.zeros((0, 3))


def _cloud(fine: np.ndarray, center: np.ndarray, params: RegistrationParams, merged: bool
           ) -> RegistrationCloud:
    """Both grids from the target grid's points; a merged cloud beyond ``max_target_points``
    goes on a coarser target grid (points on surfaces: their number falls with the voxel
    squared); the source grid is capped by a fixed random subset."""
    cap = params.max_target_points
    if merged and 0 < cap < len(fine):
        fine = _grid(fine, params.target_voxel * float(np.sqrt(len(fine) / cap)))
    coarse = _grid(fine, params.source_voxel)
    k = params.max_source_points
    if 0 < k < len(coarse):
        coarse = coarse[np.sort(np.random.default_rng(0).choice(len(coarse), k, False))]
    return RegistrationCloud(fine, coarse, center)


def registration_cloud(xyz: np.ndarray, viewpoint: np.ndarray | None,
                       params: RegistrationParams) -> RegistrationCloud:
    """Prepare one scan (map frame) for :func:`pairwise_icp`: its two voxel grids.
    ``viewpoint`` (the sensor position) is not needed by generalized ICP; kept for callers."""
    xyz = np.asarray(xyz, np.float64)
    center = xyz.mean(axis=0) if len(xyz) else np.zeros(3)
    return _cloud(_grid(xyz, params.target_voxel), center, params, merged=False)


def merge_registration(clouds: list[RegistrationCloud], corrections: list[np.ndarray],
                       weights: list[float], params: RegistrationParams) -> RegistrationCloud:
    """The registration cloud of a merged group: its members' target grids moved by their
    corrections, stacked and put on the grids again (no neighbour search here)."""
    xyz = np.concatenate([apply_rigid(c.points, m) for c, m in zip(clouds, corrections)])
    centers = [apply_rigid(c.center[None], m)[0] for c, m in zip(clouds, corrections)]
    return _cloud(_grid(xyz, params.target_voxel),
                  np.average(centers, axis=0, weights=weights), params, merged=True)


def rotation_deg(matrix: np.ndarray) -> float:
    """Rotation angle of a 4x4 (or 3x3) transform, degrees.

    atan2 of the rotation's sine (from its skew part) and cosine (from its trace): arccos of the
    trace alone loses precision near zero (1e-6 deg of noise on an identity)."""
    r = np.asarray(matrix, float)[:3, :3]
    sin = 0.5 * np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cos = (np.trace(r) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(sin, cos)))


def information_matrix(target_points: np.ndarray) -> np.ndarray:
    """6x6 information of an ICP edge from the target points of its correspondences (map frame),
    as Open3D's ``get_information_matrix`` defines it (rotation first), so the pose graph weighs
    edges as before: the sum over partners q of G(q)^T G(q), G(q) = [[q]x^T | I]."""
    q = np.asarray(target_points, float)
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    xx, yy, zz, xy, xz, yz = x @ x, y @ y, z @ z, x @ y, x @ z, y @ z
    sx, sy, sz, n = x.sum(), y.sum(), z.sum(), float(len(q))
    return np.array([
        [yy + zz, -xy, -xz, 0.0, -sz, sy],
        [-xy, xx + zz, -yz, sz, 0.0, -sx],
        [-xz, -yz, xx + yy, -sy, sx, 0.0],
        [0.0, sz, -sy, n, 0.0, 0.0],
        [-sz, 0.0, sx, 0.0, n, 0.0],
        [sy, -sx, 0.0, 0.0, 0.0, n]])


def pairwise_icp(source: RegistrationCloud, target: RegistrationCloud,
                 params: RegistrationParams, source_id: int = 0, target_id: int = 1,
                 init: np.ndarray | None = None, first_stage: int = 0) -> PairResult:
    """Generalized ICP, coarse to fine (one stage per correspondence distance), from ``init``
    (default identity: the clouds are already roughly aligned by their poses); ``first_stage``
    > 0 skips coarse stages.

    Runs in the target's centred frame (``target.center`` at the origin); the result is the map
    frame's transformation."""
    matrix = np.eye(4) if init is None else np.asarray(init, float)
    if len(source.source_points) < 3 or len(target) < 3:
        return PairResult(source_id, target_id, np.eye(4), np.zeros((6, 6)), 0.0,
                          float("inf"), False, "too few points")
    cloud, tree = target.target(params)
    moving, _ = source.source(params)
    to_target, to_map = np.eye(4), np.eye(4)  # map frame <-> the target's centred frame
    to_target[:3, 3], to_map[:3, 3] = -target.center, target.center
    from_source = np.eye(4)  # the source's centred frame -> map frame
    from_source[:3, 3] = source.center
    local = to_target @ matrix @ from_source
    last = len(params.max_correspondence) - 1
    for stage in range(min(first_stage, last), last + 1):
        result = small_gicp.align(cloud, moving, tree, local, registration_type="GICP",
                                  max_correspondence_distance=params.max_correspondence[stage],
                                  num_threads=1, max_iterations=params.max_iterations,
                                  rotation_epsilon=np.radians(params.converged_deg),
                                  translation_epsilon=params.converged_m)
        local = np.asarray(result.T_target_source)
    matrix = to_map @ local @ np.linalg.inv(from_source)
    # overlap, residual and information from the finest stage's partners
    moved = apply_rigid(source.source_points, to_target @ matrix)
    index, d2 = tree.batch_nearest_neighbor_search(moved, 1)
    index, d2 = np.asarray(index).reshape(-1), np.asarray(d2).reshape(-1)
    inlier = (index >= 0) & (d2 <= params.max_correspondence[last] ** 2)
    fitness = float(inlier.mean()) if len(inlier) else 0.0
    rmse = float(np.sqrt(d2[inlier].mean())) if inlier.any() else float("inf")
    shift_m = float(np.linalg.norm(matrix[:3, 3]))
    angle = rotation_deg(matrix)
    reason = ""
    if fitness < params.min_fitness:
        reason = f"overlap {fitness:.2f} below {params.min_fitness}"
    elif shift_m > params.max_correction_m or angle > params.max_correction_deg:
        reason = f"implausible correction {shift_m:.2f} m / {angle:.2f} deg"
    information = np.zeros((6, 6))
    if not reason:
        information = information_matrix(target.points[index[inlier]])
    return PairResult(source_id, target_id, matrix, information, fitness, rmse,
                      not reason, reason)


def _components(n: int, pairs: list[PairResult]) -> list[list[int]]:
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for p in pairs:
        if p.accepted:
            parent[root(p.source)] = root(p.target)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())


def anchor(corrections: list[np.ndarray], weights: np.ndarray, center: np.ndarray
           ) -> list[np.ndarray]:
    """Re-anchor corrections so their weighted mean about ``center`` is the identity.

    About the centroid, because a rotation about the map origin (maybe kilometres away) would
    mostly act as a translation; the mean rotation is the chordal L2 mean (scipy).
    """
    shift, unshift = np.eye(4), np.eye(4)
    shift[:3, 3], unshift[:3, 3] = -center, center
    local = [shift @ c @ unshift for c in corrections]
    mean = np.eye(4)
    mean[:3, :3] = Rotation.from_matrix([c[:3, :3] for c in local]).mean(weights).as_matrix()
    mean[:3, 3] = np.average([c[:3, 3] for c in local], axis=0, weights=weights)
    inv_mean = np.linalg.inv(mean)
    return [unshift @ inv_mean @ c @ shift for c in local]


def register_group(clouds: list[RegistrationCloud], weights: list[float] | None = None,
                   params: RegistrationParams | None = None) -> GroupResult:
    """Multiway ICP of 1-3 time-ordered neighbouring clouds; one correction per cloud.

    Edges: each neighbour pair (odometry edges) and, for three clouds, first -> last (uncertain,
    so the optimiser may prune it). Rejected edges are left out; members no accepted edge connects
    form their own components and are anchored separately (they keep their poses).
    """
    params = params or RegistrationParams()
    n = len(clouds)
    if n == 0:
        return GroupResult([], [])
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    if n == 1:
        return GroupResult([np.eye(4)], [])
    pairs = [pairwise_icp(clouds[i], clouds[i + 1], params, i, i + 1) for i in range(n - 1)]
    if n == 3 and params.loop_edges:
        # start from the chain of the two odometry edges; then only the fine stage is needed
        chained = pairs[0].accepted and pairs[1].accepted
        init = pairs[1].transformation @ pairs[0].transformation if chained else None
        pairs.append(pairwise_icp(clouds[0], clouds[2], params, 0, 2, init,
                                  first_stage=len(params.max_correspondence) - 1 if chained else 0))
    nodes = _optimise_graph(n, pairs, params, reference=0)
    corrections = list(nodes)
    for members in _components(n, pairs):
        if len(members) < 2:
            corrections[members[0]] = np.eye(4)
            continue
        center = np.average([clouds[i].center for i in members], axis=0, weights=w[members])
        anchored = anchor([nodes[i] for i in members], w[members], center)
        for i, c in zip(members, anchored):
            corrections[i] = c
    return GroupResult(corrections, pairs)


def _optimise_graph(n: int, pairs: list[PairResult], params: RegistrationParams,
                    reference: int) -> list[np.ndarray]:
    """Node poses (4x4, map frame, applied on the left of each member) from the accepted edges:
    the odometry chain as the start, then Open3D's pose-graph optimisation with ``reference``
    held fixed. An edge (s, t, T) says T ~ inv(node_t) @ node_s; edges further than one apart
    are uncertain (the optimiser may prune them)."""
    nodes = [np.eye(4)] * n
    for i in range(reference + 1, n):  # chain outwards from the reference
        odo = next((p for p in pairs if p.source == i - 1 and p.target == i and p.accepted), None)
        nodes[i] = nodes[i - 1] @ (np.linalg.inv(odo.transformation) if odo else np.eye(4))
    for i in range(reference - 1, -1, -1):
        odo = next((p for p in pairs if p.source == i and p.target == i + 1 and p.accepted), None)
        nodes[i] = nodes[i + 1] @ (odo.transformation if odo else np.eye(4))
    accepted = [p for p in pairs if p.accepted]
    if not accepted:
        return nodes
    # Open3D here, not at the top: with its plotting stack it is half a second of start-up that
    # every process importing the map builder (the calibrator's rig pairing, the CLI) paid
    import open3d as o3d

    _reg = o3d.pipelines.registration  # pose graph (legacy API)
    graph = _reg.PoseGraph()
    for node in nodes:
        graph.nodes.append(_reg.PoseGraphNode(node))
    for p in accepted:
        graph.edges.append(_reg.PoseGraphEdge(
            p.source, p.target, p.transformation, p.information,
            uncertain=(p.target - p.source) > 1))
    option = _reg.GlobalOptimizationOption(
        max_correspondence_distance=params.max_correspondence[-1],
        edge_prune_threshold=params.edge_prune_threshold, reference_node=reference)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        _reg.global_optimization(graph, _reg.GlobalOptimizationLevenbergMarquardt(),
                                 _reg.GlobalOptimizationConvergenceCriteria(), option)
    return [np.asarray(node.pose) for node in graph.nodes]


def register_chain(clouds: list[RegistrationCloud], reference: int,
                   params: RegistrationParams | None = None, loop_span: int = 2) -> GroupResult:
    """Multiway ICP of time-ordered scans with one of them held fixed (no re-anchoring).

    For a camera on the vehicle: the camera at frame i is tied to scan i, so scan i must stay
    exactly where it is and the others are registered to it (``register_group`` instead keeps the
    group's mean pose, right for a roadside map in the poses' world frame). Edges: neighbours,
    and scans up to ``loop_span`` apart (uncertain), started from the chained neighbour edges.
    Scans no accepted edge connects to the reference keep their poses (correction identity).
    """
    params = params or RegistrationParams()
    n = len(clouds)
    if not 0 <= reference < max(n, 1):
        raise ValueError(f"reference scan {reference} is not among the {n} scans")
    if n < 2:
        return GroupResult([np.eye(4)] * n, [])
    pairs = [pairwise_icp(clouds[i], clouds[i + 1], params, i, i + 1) for i in range(n - 1)]
    last = len(params.max_correspondence) - 1
    for span in range(2, loop_span + 1):
        for i in range(n - span):
            chain = [pairs[k] for k in range(i, i + span)]
            init = None
            if all(p.accepted for p in chain):
                init = np.eye(4)
                for p in chain:
                    init = p.transformation @ init
            pairs.append(pairwise_icp(clouds[i], clouds[i + span], params, i, i + span, init,
                                      first_stage=last if init is not None else 0))
    nodes = _optimise_graph(n, pairs, params, reference)
    fixed = np.linalg.inv(nodes[reference])  # held by the optimiser; exact identity here
    connected = next(c for c in _components(n, pairs) if reference in c)
    corrections = [fixed @ nodes[i] if i in connected else np.eye(4) for i in range(n)]
    corrections[reference] = np.eye(4)
    return GroupResult(corrections, pairs)
