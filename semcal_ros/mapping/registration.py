"""Multiway ICP of a group of neighbouring clouds (the paper's step 1, one level of the recursion).

The clouds of a group are already in the map frame, placed by the vehicle's poses; registration
finds small rigid corrections. Point-to-plane ICP runs between each pair of neighbours (and between
the first and the last, as a less certain loop edge), then Open3D's pose-graph optimisation makes
the pairwise results agree. Lidar alone cannot tell where the whole group sits in the map (only
where its members sit relative to each other), so the corrections are finally re-anchored such
that their weighted mean, taken about the group's centroid, is the identity: the group as a whole
stays where the poses put it, and independent pose errors average out level by level.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.mapping.filters import apply_rigid, voxel_downsample

_reg = o3d.pipelines.registration  # pose graph (legacy API)
_treg = o3d.t.pipelines.registration  # ICP (tensor API: several times faster on CPU here)


@dataclass
class RegistrationParams:
    """Parameters of the pairwise ICP (coarse-to-fine stages) and of the pose graph."""

    icp_voxels: tuple[float, ...] = (0.6, 0.3)  # voxel size of the clouds per ICP stage, metres
    max_correspondence: tuple[float, ...] = (1.2, 0.45)  # partner search distance per stage
    max_iterations: int = 30  # per stage
    relative_change: float = 1e-5  # a stage stops when fitness and rmse change less (1e-6
    # crept on for 30 iterations on some pairs without changing the result)
    max_source_points: int = 10000  # ICP moves a random subset of the source (0: all points)
    normal_radius_factor: float = 3.0  # normals from neighbours within this many voxels
    normal_max_nn: int = 20
    min_fitness: float = 0.2  # fraction of source points with a partner; less: edge dropped
    max_correction_m: float = 2.0  # an ICP result moving a cloud further is dropped
    max_correction_deg: float = 5.0
    loop_edges: bool = True  # add first -> last as an uncertain edge in groups of three
    edge_prune_threshold: float = 0.25

    def __post_init__(self) -> None:
        if len(self.icp_voxels) != len(self.max_correspondence) or not self.icp_voxels:
            raise ValueError("icp_voxels and max_correspondence need one value per ICP stage")
        if min(self.icp_voxels) <= 0 or min(self.max_correspondence) <= 0:
            raise ValueError("ICP voxel sizes and correspondence distances must be positive")
        if list(self.icp_voxels) != sorted(self.icp_voxels, reverse=True):
            raise ValueError("icp_voxels must go from coarse to fine")
        if self.normal_radius_factor <= 0 or self.max_iterations < 1:
            raise ValueError("normal_radius_factor and max_iterations must be positive")


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


@dataclass
class RegistrationCloud:
    """What ICP works on, one cloud per coarse-to-fine stage: voxel centroids (labels do not
    matter for registration) with unit normals oriented towards the sensor that saw them."""

    points: list[np.ndarray]  # per stage (M, 3) float64, map frame
    normals: list[np.ndarray]  # per stage (M, 3)
    center: np.ndarray  # centroid of the points, map frame
    _tensors: dict = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.points[-1])

    def tensor(self, stage: int, max_points: int = 0) -> o3d.t.geometry.PointCloud:
        """The stage as an Open3D tensor cloud (made once, used by every pair); with
        ``max_points`` > 0 a fixed random subset of at most that many points."""
        key = (stage, max_points)
        if key not in self._tensors:
            pts, nrm = self.points[stage], self.normals[stage]
            if 0 < max_points < len(pts):
                pick = np.sort(np.random.default_rng(0).choice(len(pts), max_points, False))
                pts, nrm = pts[pick], nrm[pick]
            pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
            pcd.point.normals = o3d.core.Tensor(nrm.astype(np.float32))
            self._tensors[key] = pcd
        return self._tensors[key]


def _voxel_normals(xyz: np.ndarray, normals: np.ndarray, voxel: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centroids with averaged, renormalised normals; voxels whose normals cancel (both
    sides of a thin wall, sharp edges) are dropped."""
    merged = voxel_downsample(LabelledCloud(xyz, None, {"nx": normals[:, 0], "ny": normals[:, 1],
                                                        "nz": normals[:, 2]}), voxel)
    n = np.stack([merged.extra["nx"], merged.extra["ny"], merged.extra["nz"]], axis=1)
    length = np.linalg.norm(n, axis=1)
    keep = length > 0.5
    return merged.xyz[keep], n[keep] / length[keep, None]


def registration_cloud(xyz: np.ndarray, viewpoint: np.ndarray, params: RegistrationParams
                       ) -> RegistrationCloud:
    """Prepare one scan (map frame, seen from ``viewpoint``) for :func:`pairwise_icp`.

    Normals are searched once, on the finest stage (Open3D's neighbour search within
    ``normal_radius_factor`` voxels, numpy voxel grid: faster here than Open3D's tensor grid),
    and turned towards the sensor; coarser stages and merged clouds (:func:`merge_registration`)
    average them instead of searching again on ever larger clouds.
    """
    xyz = np.asarray(xyz, np.float64)
    finest = params.icp_voxels[-1]
    pts = voxel_downsample(LabelledCloud(xyz), finest).xyz if len(xyz) else np.zeros((0, 3))
    nrm = np.zeros_like(pts)
    if len(pts) >= 3:
        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
        pcd.estimate_normals(max_nn=params.normal_max_nn,
                             radius=params.normal_radius_factor * finest)
        nrm = pcd.point.normals.numpy().astype(np.float64)
        towards = np.einsum("ij,ij->i", np.asarray(viewpoint, float) - pts, nrm)
        nrm[towards < 0] *= -1.0
    points, normals = [], []
    for voxel in params.icp_voxels[:-1]:
        p, n = _voxel_normals(pts, nrm, voxel) if len(pts) else (pts, nrm)
        points.append(p)
        normals.append(n)
    points.append(pts)
    normals.append(nrm)
    center = xyz.mean(axis=0) if len(xyz) else np.zeros(3)
    return RegistrationCloud(points, normals, center)


def _rotation_only(matrix: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = matrix[:3, :3]
    return out


def merge_registration(clouds: list[RegistrationCloud], corrections: list[np.ndarray],
                       weights: list[float], params: RegistrationParams) -> RegistrationCloud:
    """The registration cloud of a merged group, from its members' (no new normal search):
    members moved by their corrections, stacked and voxel-averaged per stage."""
    points, normals = [], []
    for stage, voxel in enumerate(params.icp_voxels):
        xyz = np.concatenate([apply_rigid(c.points[stage], m) for c, m in zip(clouds, corrections)])
        nrm = np.concatenate([apply_rigid(c.normals[stage], _rotation_only(m))
                              for c, m in zip(clouds, corrections)])
        p, n = _voxel_normals(xyz, nrm, voxel) if len(xyz) else (xyz, nrm)
        points.append(p)
        normals.append(n)
    centers = [apply_rigid(c.center[None], m)[0] for c, m in zip(clouds, corrections)]
    return RegistrationCloud(points, normals, np.average(centers, axis=0, weights=weights))


def rotation_deg(matrix: np.ndarray) -> float:
    """Rotation angle of a 4x4 (or 3x3) transform, degrees.

    atan2 of the rotation's sine (from its skew part) and cosine (from its trace): arccos of the
    trace alone loses precision near zero (1e-6 deg of noise on an identity)."""
    r = np.asarray(matrix, float)[:3, :3]
    sin = 0.5 * np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cos = (np.trace(r) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(sin, cos)))


def pairwise_icp(source: RegistrationCloud, target: RegistrationCloud,
                 params: RegistrationParams, source_id: int = 0, target_id: int = 1,
                 init: np.ndarray | None = None, first_stage: int = 0) -> PairResult:
    """Point-to-plane ICP, coarse to fine, from ``init`` (default identity: the clouds are
    already roughly aligned by their poses); ``first_stage`` > 0 skips coarse stages."""
    transformation = o3d.core.Tensor(np.eye(4) if init is None else np.asarray(init, float))
    if len(source) < 3 or len(target) < 3:
        return PairResult(source_id, target_id, np.eye(4), np.zeros((6, 6)), 0.0,
                          float("inf"), False, "too few points")
    criteria = _treg.ICPConvergenceCriteria(relative_fitness=params.relative_change,
                                            relative_rmse=params.relative_change,
                                            max_iteration=params.max_iterations)
    method = _treg.TransformationEstimationPointToPlane()
    result = None
    last = len(params.icp_voxels) - 1
    cap = params.max_source_points  # bounds the cost of big merged clouds at high levels
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        for stage in range(min(first_stage, last), last + 1):
            # the search cost grows with distance^3 x density: coarse clouds for far partners
            result = _treg.icp(source.tensor(stage, cap), target.tensor(stage),
                               params.max_correspondence[stage], transformation, method,
                               criteria)
            transformation = result.transformation
    matrix = transformation.numpy().astype(np.float64)
    fitness, rmse = float(result.fitness), float(result.inlier_rmse)
    shift = float(np.linalg.norm(matrix[:3, 3]))
    angle = rotation_deg(matrix)
    reason = ""
    if fitness < params.min_fitness:
        reason = f"overlap {fitness:.2f} below {params.min_fitness}"
    elif shift > params.max_correction_m or angle > params.max_correction_deg:
        reason = f"implausible correction {shift:.2f} m / {angle:.2f} deg"
    information = np.zeros((6, 6))
    if not reason:
        information = _treg.get_information_matrix(
            source.tensor(last, cap), target.tensor(last), params.max_correspondence[last],
            transformation).numpy().astype(np.float64)
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
                                  first_stage=len(params.icp_voxels) - 1 if chained else 0))
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
    last = len(params.icp_voxels) - 1
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
