"""Registration of a labelled map to a label image: Nelder-Mead over the camera pose.

``calibrate`` is the whole method of the paper in one call: the map is prepared once, the loss is
minimised by Nelder-Mead stages from coarse (quarter image, an eighth of the points) to fine (full
image, all points), and verification runs from noisy initial guesses guard against the non-convex
loss: the lowest loss wins and the accepted runs' spread says how well-posed the result is.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import minimize

from semcal_ros.camera import CameraModel
from semcal_ros.cloud import LabelledCloud
from semcal_ros.labels import INVALID, LabelMapping
from semcal_ros.loss import LabelLoss
from semcal_ros.params import CalibrationParams
from semcal_ros.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.render import PreparedMap, make_view, prepare_map
from semcal_ros.render.fast import render


class Cancelled(Exception):
    """Raised inside ``calibrate`` when ``should_stop()`` returned True."""


@dataclass(frozen=True)
class Progress:
    stage: str
    evaluations: int
    best_loss: float
    best_pose: Pose


@dataclass(frozen=True)
class RunResult:
    """One schedule from one start: the final loss is at full resolution, comparable across runs."""

    start: Pose
    pose: Pose
    loss: float
    evaluations: int


@dataclass
class CalibrationResult:
    pose: Pose
    loss: float
    evaluations: int
    seconds: float
    history: list[tuple[int, int, float]] = field(default_factory=list)  # (run, stage, loss)
    runs: list[RunResult] = field(default_factory=list)
    accepted: int = 1
    spread_translation_m: float = 0.0
    spread_rotation_deg: float = 0.0

    def to_dict(self) -> dict:
        """The fields a result pose YAML adds to the pose itself."""
        return {
            "loss": float(self.loss),
            "evaluations": int(self.evaluations),
            "seconds": round(float(self.seconds), 3),
            "rpy_deg": [float(v) for v in self.pose.body_rpy_deg()],
            "verification": {
                "runs": len(self.runs),
                "accepted": int(self.accepted),
                "spread_translation_m": float(self.spread_translation_m),
                "spread_rotation_deg": float(self.spread_rotation_deg),
            },
        }


@dataclass
class _Stage:
    pmap: PreparedMap
    camera: CameraModel
    loss: LabelLoss
    splat_lambda: float
    radius_max: float
    bounds: np.ndarray
    depth_falloff: float


class _Tracker:
    """Counts evaluations, records history, reports progress, honours cancellation.

    Progress carries the best loss and pose of the stage being run: losses of different stages
    (resolutions) are not comparable, so a single running minimum would mislead.
    """

    def __init__(self, progress: Callable[[Progress], None] | None,
                 should_stop: Callable[[], bool] | None, interval: float = 0.25) -> None:
        self.progress, self.should_stop, self.interval = progress, should_stop, interval
        self.evaluations = 0
        self.history: list[tuple[int, int, float]] = []
        self.stage = "start"
        self.stage_loss = np.inf
        self.stage_pose: Pose | None = None
        self._last_report = 0.0

    def begin_stage(self, name: str) -> None:
        self.stage, self.stage_loss, self.stage_pose = name, np.inf, None

    def record(self, run: int, stage: int, loss: float, pose: Pose) -> None:
        if self.should_stop is not None and self.should_stop():
            raise Cancelled("calibration cancelled")
        self.evaluations += 1
        self.history.append((run, stage, loss))
        if loss < self.stage_loss:
            self.stage_loss, self.stage_pose = loss, pose
        now = time.monotonic()
        if now - self._last_report >= self.interval:
            self._last_report = now
            self.report()

    def report(self) -> None:
        if self.progress is not None and self.stage_pose is not None:
            self.progress(Progress(self.stage, self.evaluations, float(self.stage_loss),
                                   self.stage_pose))


class Registration:
    """A map, a target and a camera made ready for many loss evaluations."""

    def __init__(self, map_cloud: LabelledCloud, target: np.ndarray, camera: CameraModel,
                 initial: Pose, params: CalibrationParams, mapping: LabelMapping | None = None) -> None:
        mapping = mapping or LabelMapping()
        target = np.asarray(target)
        if target.ndim != 2 or target.dtype != np.uint8:
            raise ValueError(f"label image must be a single-channel uint8 image, got {target.dtype} "
                             f"with shape {target.shape}")
        if target.shape != (camera.height, camera.width):
            raise ValueError(f"label image is {target.shape[1]}x{target.shape[0]} but camera_info "
                             f"says {camera.width}x{camera.height}")
        if len(map_cloud) and not np.all(np.isfinite(map_cloud.xyz)):
            bad = int((~np.all(np.isfinite(map_cloud.xyz), axis=1)).sum())
            raise ValueError(f"map contains {bad} NaN or infinite points")
        self.params = params
        self.initial = initial
        radius = params.render.crop_radius or None
        self.pmap = prepare_map(map_cloud, mapping, center=initial.translation, radius=radius)
        aligned_target = mapping.map_image(target)
        if np.all(aligned_target == INVALID):
            raise ValueError("label image has no pixel of a class the map can match")
        self.splat_lambda = params.render.splat_lambda_for(self.pmap.point_spacing(), camera.fx)
        self.stages = [self._stage(aligned_target, camera, s) for s in range(len(params.schedule.scales))]
        # free parameters (x, y, z, [roll], pitch, yaw) and their search bounds
        sp = params.search
        self.free = np.array([0, 1, 2] + ([3] if sp.free_roll else []) + [4, 5])
        bounds = np.array([*sp.bound_xyz, np.radians(sp.bound_roll_deg),
                           np.radians(sp.bound_pitch_deg), np.radians(sp.bound_yaw_deg)])
        self.scale = bounds[self.free]

    def _stage(self, aligned_target: np.ndarray, camera: CameraModel, index: int) -> _Stage:
        sch, rp = self.params.schedule, self.params.render
        factor = int(sch.scales[index])
        cam = camera.scaled(factor)
        off = factor // 2
        target = np.ascontiguousarray(aligned_target[off::factor, off::factor][:cam.height, :cam.width])
        radius_max = max(1.0, rp.radius_max / factor)
        pmap = self.pmap.subset(sch.point_fractions[index])
        # discs grow with the point spacing of the thinned map, as if it were the full map
        thinning = np.sqrt(len(self.pmap) / len(pmap))
        return _Stage(
            pmap=pmap, camera=cam, loss=LabelLoss(target, self.params.loss),
            splat_lambda=self.splat_lambda / factor * thinning,
            depth_falloff=rp.depth_falloff if factor == 1 else rp.depth_falloff_coarse,
            radius_max=radius_max, bounds=np.asarray(cam.normalized_bounds(margin_px=radius_max)),
        )

    def render(self, pose: Pose, stage: int = -1) -> np.ndarray:
        st = self.stages[stage]
        rp = self.params.render
        view = make_view(st.camera, pose, st.pmap.origin, st.splat_lambda, st.radius_max,
                         rp.near, rp.far, st.bounds, st.depth_falloff, rp.core_fraction)
        return render(st.pmap, view)

    def loss(self, pose: Pose, stage: int = -1) -> float:
        return self.stages[stage].loss(self.render(pose, stage))

    def coverage(self, pose: Pose, stage: int = 0) -> float:
        return self.stages[stage].loss.evaluate(self.render(pose, stage))[1]

    def pose_at(self, center: np.ndarray, s: np.ndarray) -> Pose:
        v = center.copy()
        v[self.free] += self.scale * s
        return Pose.from_vector(v)

    def run(self, start: Pose, tracker: _Tracker, run_index: int, label: str) -> RunResult:
        """The coarse-to-fine schedule from one start, then the paper's restarts of the last
        stage from its own result while they still lower the loss."""
        sch = self.params.schedule
        center = start.vector()
        evals0 = tracker.evaluations
        n_stages = len(sch.scales)
        for k in range(n_stages):
            tracker.begin_stage(f"{label}, stage {k + 1}/{n_stages} (1/{sch.scales[k]} resolution)")
            center = self._nelder_mead(k, center, tracker, run_index)
        last = n_stages - 1
        name = tracker.stage
        for r in range(sch.final_restarts):
            before = tracker.stage_loss
            tracker.stage = f"{name}, restart {r + 1}"  # same stage: its best carries over
            center = self._nelder_mead(last, center, tracker, run_index)
            if before - tracker.stage_loss <= sch.fatol[last]:
                break
        tracker.report()
        return RunResult(start, tracker.stage_pose, float(tracker.stage_loss),
                         tracker.evaluations - evals0)

    def _nelder_mead(self, k: int, center: np.ndarray, tracker: _Tracker, run_index: int) -> np.ndarray:
        """One Nelder-Mead search of stage ``k`` around ``center``; returns the best pose seen."""
        sch = self.params.schedule

        def objective(s: np.ndarray) -> float:
            pose = self.pose_at(center, s)
            value = self.loss(pose, k)
            tracker.record(run_index, k, value, pose)
            return value

        n = len(self.free)
        minimize(objective, np.zeros(n), method="Nelder-Mead",
                 options={"initial_simplex": _initial_simplex(n) * sch.simplex[k],
                          "xatol": sch.xatol, "fatol": sch.fatol[k],
                          "maxfev": sch.max_evaluations[k]})
        return tracker.stage_pose.vector()  # the best seen, not Nelder-Mead's last vertex


def _initial_simplex(n: int) -> np.ndarray:
    """n+1 vertices centred on the origin reaching +1 in every coordinate: the paper builds the
    simplex by adding and subtracting the full parameter range around the initial guess."""
    vertices = np.vstack([np.zeros(n), np.eye(n)])
    vertices -= vertices.mean(axis=0)
    return vertices / vertices.max(axis=0)


def _yaw_candidates(reg: Registration, initial: Pose, tracker: _Tracker) -> list[Pose]:
    sp = reg.params.search
    v = initial.vector()
    scored = []
    tracker.begin_stage("yaw grid search")
    for yaw in np.arange(-180.0, 180.0, sp.yaw_search_step_deg):
        cand = v.copy()
        cand[5] = v[5] + np.radians(yaw)
        pose = Pose.from_vector(cand)
        value = reg.loss(pose, 0)
        tracker.record(-1, 0, value, pose)
        scored.append((value, yaw, pose))
    scored.sort(key=lambda item: item[0])
    return [pose for _, _, pose in scored[: sp.yaw_search_keep]]


def calibrate(map_cloud: LabelledCloud, target: np.ndarray, camera: CameraModel, initial: Pose,
              params: CalibrationParams | None = None, mapping: LabelMapping | None = None,
              seed: int | None = None, progress: Callable[[Progress], None] | None = None,
              should_stop: Callable[[], bool] | None = None) -> CalibrationResult:
    """Find the camera pose in the map frame (see the module docstring)."""
    t0 = time.perf_counter()
    params = params or CalibrationParams()
    reg = Registration(map_cloud, target, camera, initial, params, mapping)
    tracker = _Tracker(progress, should_stop)
    if not params.search.yaw_search and reg.coverage(initial) < params.loss.min_coverage:
        raise ValueError("no map point in view at the initial pose (check the initial pose, "
                         "its frame and the map)")
    rng = np.random.default_rng(seed)
    starts = _yaw_candidates(reg, initial, tracker) if params.search.yaw_search else [initial]
    runs = [reg.run(s, tracker, i, f"run {i + 1}") for i, s in enumerate(starts)]
    best = min(runs, key=lambda r: r.loss)
    vp = params.verification
    for j in range(vp.starts):
        noise = rng.uniform(-1.0, 1.0, len(reg.free)) * vp.noise
        start = reg.pose_at(best.start.vector(), noise)
        index = len(runs)
        runs.append(reg.run(start, tracker, index, f"verification {j + 1}/{vp.starts}"))
    best = min(runs, key=lambda r: r.loss)
    accepted = [r for r in runs if r.loss <= best.loss * (1.0 + vp.loss_margin) + vp.loss_margin_abs]
    dt = np.array([translation_error(r.pose, best.pose) for r in accepted])
    dr = np.array([rotation_error_deg(r.pose, best.pose) for r in accepted])
    return CalibrationResult(
        pose=best.pose, loss=best.loss, evaluations=tracker.evaluations,
        seconds=time.perf_counter() - t0, history=tracker.history, runs=runs,
        accepted=len(accepted), spread_translation_m=float(np.sqrt(np.mean(dt**2))),
        spread_rotation_deg=float(np.sqrt(np.mean(dr**2))),
    )
