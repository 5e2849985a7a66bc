"""Drift check: is a camera's calibration still right, judged from its newest label image.

Cameras get knocked, heat-soaked and re-aimed. Recalibrating every few minutes would cost a full
search each time; a check asks a cheaper question. It has two forms:

* **from a reference** (every check after the monitor's first, ``semcal check --reference``):
  :func:`check_motion` measures the camera's motion from the reference label image to the new one
  with the map's depth at the calibration (:mod:`semcal_ros.engine.label_motion`: chamfer
  matching of class boundaries, no render), with an uncertainty from the two image halves; the
  motion counts when it stands ``motion_sigmas`` uncertainties out;
* **against the map** (the first check, ``semcal check`` alone): :func:`check_drift` runs a
  Nelder-Mead search (:class:`~semcal_ros.engine.search.Search`, the engine's own) around the
  calibration inside small bounds at 1/``scale`` resolution (pan and tilt first, then every free
  axis); a pose that lowers the loss by ``min_gain_absolute`` (relative to its excess over the
  loss's floor) is sized at full resolution and counts only if the full-resolution loss drops by
  ``min_gain_full`` too. Such a check keeps its image and the map's depth: the reference view.

Levels: ``ok``; ``warn`` when the drift is above ``warn_translation_m`` or ``warn_rotation_deg``;
``error`` above ``error_translation_m`` / ``error_rotation_deg``, beyond the check's bounds, or an
image that no longer matches its reference (recalibrate); ``unknown`` when the check cannot judge
(no label image, the map covers too little of it, a degenerate view). The thresholds and how they
were measured are in docs/drift.md. No ROS here: ``semcal check`` and the ``calibration_monitor``
node both call :class:`DriftChecker`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.config import apply_flat, load_node_params
from semcal_ros.engine.label_motion import Motion, ReferenceView, estimate_motion
from semcal_ros.engine.labels import INVALID, LabelMapping
from semcal_ros.engine.search import EvaluationCounter, Search
from semcal_ros.engine.params import CalibrationParams, ScheduleParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.engine.problem import Evaluation, Problem, mapping_for
from semcal_ros.engine.render import PreparedMap, prepare_map
from semcal_ros.engine.render.fast import render_with_keys
from semcal_ros.errors import InputError, UnknownParameter

LEVELS = ("ok", "warn", "error", "unknown")
SIZE_STAGE = 2  # the check's schedule: pan and tilt, every axis, the size of a counted drift
#: diagnostic_msgs/DiagnosticStatus levels (OK, WARN, ERROR, STALE for "cannot judge")
DIAGNOSTIC_LEVEL = {"ok": 0, "warn": 1, "error": 2, "unknown": 3}


@dataclass(frozen=True)
class DriftParams:
    """What one check costs and when it raises; docs/drift.md has the measurements."""

    scale: int = 4  # renders at 1/scale resolution
    bound_m: float = 0.25  # search bounds around the calibration: translation per axis
    bound_deg: float = 0.75  # ... and pitch, yaw (and roll when the engine frees it)
    simplex: float = 0.3  # initial simplex, as a fraction of the bounds
    max_evaluations: int = 50  # renders of the search (plus one at the calibration)
    turn_share: float = 0.4  # of them spent on pan and tilt alone first
    min_gain: float = 0.05  # relative loss drop (beyond the reference's) that counts as drift
    min_gain_absolute: float = 0.2  # the same without a reference check (semcal check alone)
    # a screened drift counts only if, at the sizing's (full) resolution, the sized pose also
    # lowers the loss by this much below the calibration's (relative to its excess over the
    # floor): the resolution that decides centimetres decides, not the coarse screen alone
    min_gain_full: float = 0.15
    # with a reference image: the camera's motion since it, from the two label images
    # (engine/label_motion.py), counts when it exceeds motion_sigmas x its own uncertainty (the
    # two image halves) and explains motion_min_gain of the boundary charge at no motion
    motion_sigmas: float = 3.0
    motion_min_gain: float = 0.05
    # ... and a new image whose boundaries stay this far from the reference's after the best
    # motion (mean charge, 1 = everything beyond 6 px) no longer shows the reference's scene
    motion_max_cost: float = 0.5
    min_coverage: float = 0.10  # the map must cover this share of the image's scene pixels
    # a counted drift is sized by a search at size_scale from the coarse estimate (the coarse
    # one undersized the demo's knock by half: at 1/4 resolution 0.3 deg is 0.6 px)
    size_scale: int = 1  # its resolution (1/2 sized the demo's knock 1.9 cm / 0.18 deg)
    size_evaluations: int = 100  # its renders (0: off, the coarse estimate is the size; 40
    #                              at full resolution sized it 1.6 cm / 0.23 deg)
    size_simplex: float = 0.1  # its initial simplex, fraction of the bounds
    warn_translation_m: float = 0.03
    warn_rotation_deg: float = 0.1
    error_translation_m: float = 0.15
    error_rotation_deg: float = 0.5

    def __post_init__(self) -> None:
        for name in ("bound_m", "bound_deg", "simplex", "size_simplex", "warn_translation_m",
                     "warn_rotation_deg", "error_translation_m", "error_rotation_deg",
                     "motion_sigmas"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"drift.{name} must be a finite number > 0, got {value}")
        for name in ("min_gain", "min_gain_absolute", "min_gain_full", "min_coverage",
                     "turn_share", "motion_min_gain", "motion_max_cost"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value < 1):
                raise ValueError(f"drift.{name} must be in [0, 1), got {value}")
        for name in ("scale", "size_scale"):
            value = getattr(self, name)
            if int(value) != value or not 1 <= value <= 16:
                raise ValueError(f"drift.{name} must be an integer in 1..16, got {value}")
        if int(self.max_evaluations) != self.max_evaluations or self.max_evaluations < 1:
            raise ValueError(f"drift.max_evaluations must be an integer >= 1, got "
                             f"{self.max_evaluations}")
        if int(self.size_evaluations) != self.size_evaluations or self.size_evaluations < 0:
            raise ValueError(f"drift.size_evaluations must be an integer >= 0, got "
                             f"{self.size_evaluations}")
        if self.error_translation_m < self.warn_translation_m or \
                self.error_rotation_deg < self.warn_rotation_deg:
            raise ValueError("drift.error_* thresholds must not be below the warn_* ones")
        if self.error_translation_m > self.bound_m or self.error_rotation_deg > self.bound_deg:
            raise ValueError(f"drift.error_* thresholds must lie inside the search bounds "
                             f"(bound_m {self.bound_m}, bound_deg {self.bound_deg})")

    @classmethod
    def from_file(cls, path: str | None, node: str = "calibration_monitor") -> "DriftParams":
        """The ``drift:`` group of a ROS 2 parameter file (config/calibration_monitor.yaml); an
        unknown name in it is an error naming it."""
        if not path:
            return cls()
        flat = {k[len("drift."):]: v for k, v in load_node_params(path, node).items()
                if k.startswith("drift.")}
        try:
            return apply_flat(cls(), flat, strict=True)
        except UnknownParameter as exc:
            raise InputError(f"{path}: drift group: {exc}") from None
        except ValueError as exc:  # a value a parameter cannot take: its check names it
            raise InputError(f"{path}: {exc}") from None


@dataclass(frozen=True)
class DriftReport:
    level: str  # "ok" | "warn" | "error" | "unknown" (cannot judge)
    message: str  # one line: the verdict and why
    calibrated: Pose
    estimated: Pose | None = None  # best pose the search found (None: cannot judge)
    drift_translation_m: float = 0.0
    drift_rotation_deg: float = 0.0
    drift_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # map frame
    loss_calibrated: float = math.nan
    loss_best: float = math.nan
    coverage: float = 0.0
    evaluations: int = 0
    seconds: float = 0.0
    raw_vector: np.ndarray | None = None  # where the search ended (before any reference)
    raw_gain: float = 0.0  # its relative loss drop (before any reference)
    full_gain: float = math.nan  # the sized pose's relative loss drop at full resolution
    # a check against the map keeps the image and the map's depth at the calibration: the
    # reference view later checks measure the camera's motion from (None: not kept)
    view: ReferenceView | None = None
    motion: Motion | None = None  # a check against a reference view: the motion it measured

    @property
    def judged(self) -> bool:
        return self.level != "unknown"

    def summary(self) -> str:
        """One line for logs and ``semcal check``."""
        if not self.judged:
            return f"CANNOT JUDGE: {self.message}"
        return (f"{self.level.upper()}: {self.message} (loss {self.loss_calibrated:.5f} -> "
                f"{self.loss_best:.5f}, {self.evaluations} renders, {self.seconds:.2f} s)")

    def to_dict(self) -> dict:
        t = self.estimated
        return {
            "level": self.level, "message": self.message,
            "drift_translation_m": round(self.drift_translation_m, 4),
            "drift_rotation_deg": round(self.drift_rotation_deg, 4),
            "drift_xyz_m": [round(v, 4) for v in self.drift_xyz_m],
            "loss_calibrated": float(self.loss_calibrated), "loss_best": float(self.loss_best),
            "coverage": round(self.coverage, 4), "evaluations": self.evaluations,
            **({} if math.isnan(self.full_gain) else
               {"full_resolution_gain": round(float(self.full_gain), 4)}),
            **({} if self.motion is None else {"motion": {
                "angle_deg": round(self.motion.angle_deg, 4),
                "angle_sigma_deg": round(self.motion.angle_sigma_deg, 4),
                "distance_m": round(self.motion.distance_m, 4),
                "distance_sigma_m": round(self.motion.distance_sigma_m, 4),
                "gain": round(self.motion.gain, 4), "samples": self.motion.samples}}),
            "seconds": round(self.seconds, 3),
            **({"estimated": {"translation": [float(v) for v in t.translation],
                              "rotation": [float(v) for v in t.quaternion]}} if t else {}),
        }


def check_params(engine: CalibrationParams, drift: DriftParams) -> CalibrationParams:
    """The engine parameters of a check: the engine's loss, render and label settings, but one
    search stage at the check's resolution inside the check's small bounds."""
    first = max(1, int(round(drift.max_evaluations * drift.turn_share)))
    rest = max(1, int(drift.max_evaluations) - first)
    # stages 0 and 1 at the check's resolution (pan/tilt, then all axes); the full-resolution
    # stage the schedule must end with is never searched
    # stage 2 (at size_scale) sizes a counted drift; the full-resolution stage the schedule
    # must end with is never searched
    scales = (int(drift.scale),) * 2 + (int(drift.size_scale),) + \
        ((1,) if drift.size_scale != 1 else ())
    n = len(scales)
    size = max(1, int(drift.size_evaluations))
    schedule = ScheduleParams(scales=scales,
                              simplex=(drift.simplex,) * 2 + (drift.size_simplex,) * (n - 2),
                              fatol=(1e-6,) * n, max_evaluations=(first, rest, size, size)[:n],
                              restarts=(0,) * n, xatol=1e-2)
    search = replace(engine.search, bound_xyz=(drift.bound_m,) * 3,
                     bound_pitch_deg=drift.bound_deg, bound_yaw_deg=drift.bound_deg,
                     bound_roll_deg=drift.bound_deg, yaw_search=False)
    return replace(engine, schedule=schedule, search=search)


def unknown(calibrated: Pose, message: str, t0: float | None = None) -> DriftReport:
    """A check that cannot judge, and why."""
    seconds = time.perf_counter() - t0 if t0 is not None else 0.0
    return DriftReport("unknown", message, calibrated, seconds=seconds)


def _search(search: Search, problem: Problem, calibrated: Pose, dp: DriftParams
            ) -> tuple[np.ndarray, float]:
    """Pan and tilt first, then every free axis: a knock turns the view far more than it shifts
    it (0.2 deg moves a point 30 m away by 10 cm, a 5 cm shift by 5 cm), and a two-parameter
    search finds that turn in a few renders where a five-parameter one spends them all on the
    simplex."""
    free, scale = search.free, search.scale
    turn = np.isin(free, (4, 5))
    search.free, search.scale = free[turn], scale[turn]  # this check's own Search
    vec, loss = search.nelder_mead(0, calibrated.vector(), 0)  # stage 0: pan and tilt
    search.free, search.scale = free, scale
    vec2, loss2 = search.nelder_mead(1, vec, 0)  # stage 1, same resolution: every free axis
    return (vec2, loss2) if loss2 < loss else (vec, loss)


def _size(search: Search, problem: Problem, estimate: np.ndarray, dp: DriftParams
          ) -> np.ndarray:
    """A screened drift's size: every free axis searched at ``size_scale`` (full) resolution
    from the coarse ``estimate``. At 1/4 resolution a 0.3 deg pan is 0.6 px: the coarse
    minimum finds the direction of a knock but not its size (the demo's 5 cm / 0.3 deg knock
    came out 2.2 cm / 0.13 deg)."""
    vec, loss = search.nelder_mead(SIZE_STAGE, estimate, 0, max_evaluations=dp.size_evaluations)
    return vec if loss < problem.loss(Pose.from_vector(estimate), SIZE_STAGE) else estimate


def _relative_gain(problem: Problem, origin: Pose, found: Pose, stage: int) -> float:
    """How much lower the loss is at ``found`` than at ``origin``, relative to the loss's excess
    over its floor at ``origin`` (0 for L2, above 0 for the likelihood): the share of what a
    perfect match could still gain that the move gains."""
    at_origin = problem.render(origin, stage)
    loss0 = float(problem.level(stage).loss(at_origin))
    excess = loss0 - float(problem.level(stage).loss.floor(at_origin))
    return (loss0 - problem.loss(found, stage)) / excess if excess > 0 else 0.0


def graded(what: str, dt: float, dr: float, dp: DriftParams) -> tuple[str, str]:
    """The level of a counted drift of ``dt`` m / ``dr`` deg (``what`` describes it) and why."""
    if dt > dp.error_translation_m or dr > dp.error_rotation_deg:
        return "error", (f"{what} above {dp.error_translation_m * 100:.0f} cm / "
                         f"{dp.error_rotation_deg:g} deg")
    if dt > dp.warn_translation_m or dr > dp.warn_rotation_deg:
        return "warn", (f"{what} above {dp.warn_translation_m * 100:.0f} cm / "
                        f"{dp.warn_rotation_deg:g} deg")
    return "ok", (f"{what}, within {dp.warn_translation_m * 100:.0f} cm / "
                  f"{dp.warn_rotation_deg:g} deg")


def check_drift(problem: Problem, calibrated: Pose, drift: DriftParams | None = None,
                reference: DriftReport | None = None) -> DriftReport:
    """One check on a problem built with :func:`check_params` (its stage 0 is the check's
    resolution); see the module docstring.

    ``reference`` is a check of the same calibration on an image known to match it (the first
    one after the calibration). A coarse search does not end exactly at the calibration even then
    (reduced resolution moves the loss's minimum by a few cm / 0.1-0.2 deg, measured in
    docs/drift.md), nor does the full-resolution one when the loss is biased (the likelihood on
    ideal labels: a few cm); with a reference, drift and gains are counted from where the
    reference's searches ended, so that offset is not reported as drift. (A reference that
    kept its view is used by :func:`check_motion` instead.)"""
    dp = drift or DriftParams()
    t0 = time.perf_counter()
    # one render at the calibration serves its loss, coverage and floor
    at_calibration = problem.render(calibrated, 0)
    start = Evaluation(*map(float, problem.level(0).loss.evaluate(at_calibration)))
    floor = problem.level(0).loss.floor(at_calibration)
    if start.coverage < dp.min_coverage:
        return unknown(calibrated, f"the map covers {start.coverage * 100:.0f} % of the image at "
                                   f"the calibration (< {dp.min_coverage * 100:.0f} %)", t0)
    if problem.degenerate(start):
        return unknown(calibrated, f"degenerate view at the calibration (loss {start.loss:.3g})",
                       t0)
    counter = EvaluationCounter(None, None)
    search = Search(problem, counter)
    search.confine(calibrated)  # the check's bounds hold: a larger move is reported at them
    vec, loss_best = _search(search, problem, calibrated, dp)
    if loss_best >= start.loss:
        vec, loss_best = calibrated.vector(), start.loss
    # the drop relative to the loss's excess over its floor (0 for L2): a loss whose perfect
    # match is not 0 (the likelihood) would otherwise need a larger move to count
    excess = start.loss - floor
    gain = (start.loss - loss_best) / excess if excess > 0 else 0.0
    raw_vec, raw_gain = vec, gain
    referenced = reference is not None and reference.raw_vector is not None
    if referenced:
        assert reference is not None and reference.raw_vector is not None
        vec = vec - (reference.raw_vector - reference.calibrated.vector())
        gain -= reference.raw_gain
    offset = (raw_vec - calibrated.vector())[search.free] / search.scale
    at_bound = bool(np.any(np.abs(offset) > 0.95))
    screened = gain >= (dp.min_gain if referenced else dp.min_gain_absolute)
    counted, full_gain = screened, math.nan
    if screened and not at_bound and dp.size_evaluations > 0:
        vec = _size(search, problem, vec, dp)
        full_gain = _relative_gain(problem, calibrated, Pose.from_vector(vec), SIZE_STAGE)
        counted = full_gain >= dp.min_gain_full
    best = Pose.from_vector(vec)
    dt = translation_error(best, calibrated)
    dr = rotation_error_deg(best, calibrated)
    seconds = time.perf_counter() - t0
    what = f"drift {dt * 100:.1f} cm / {dr:.2f} deg"
    if screened and at_bound:
        level, why = "error", (f"{what} at the check's bounds ({dp.bound_m * 100:.0f} cm / "
                               f"{dp.bound_deg:g} deg): moved further, recalibrate")
    elif counted:
        level, why = graded(what, dt, dr, dp)
    elif screened:
        level, why = "ok", (f"no clearly better pose nearby (the best, {what} away, lowers "
                            f"the loss at full resolution by {full_gain * 100:.1f} % < "
                            f"{dp.min_gain_full * 100:.0f} %)")
    else:
        need = dp.min_gain if referenced else dp.min_gain_absolute
        level, why = "ok", (f"no clearly better pose nearby (the best, {what} away, lowers "
                            f"the loss by {gain * 100:.1f} % < {need * 100:.0f} %)")
    if counted or (screened and at_bound):
        vec_d = best.translation - calibrated.translation
    else:
        dt, dr, vec_d = 0.0, 0.0, np.zeros(3)
    return DriftReport(level, why, calibrated, best, float(dt), float(dr),
                       (float(vec_d[0]), float(vec_d[1]), float(vec_d[2])), float(start.loss),
                       float(loss_best),
                       float(start.coverage), counter.evaluations + 1, seconds,
                       raw_vector=raw_vec, raw_gain=float(raw_gain),
                       full_gain=float(full_gain),
                       # only a check without a reference can become one (DriftWatch)
                       view=reference_view(problem, calibrated) if reference is None else None)


def reference_view(problem: Problem, calibrated: Pose) -> ReferenceView:
    """The problem's label image and the map's depth at ``calibrated`` (one full-resolution
    render): what a later check measures the camera's motion against."""
    view = problem.level(-1).setup.view(calibrated)
    # every disc drawn at its centre's range (no depth falloff across it): the z-buffer then
    # holds the range of the point seen there, not up to 1.3 x that at a disc's rim
    view = replace(view, disc_falloff=np.ones_like(view.disc_falloff))
    labels, keys = render_with_keys(problem.pmap, view)
    depth = np.where(labels != INVALID, (keys >> 8).astype(np.float32) / 1000.0, np.nan)
    return ReferenceView(problem.target, depth.astype(np.float32))


def check_motion(reference: DriftReport, labels: np.ndarray, camera: CameraModel,
                 calibrated: Pose, dp: DriftParams) -> DriftReport:
    """One check from a reference that kept its view: the camera's motion from the reference
    image to ``labels`` (aligned classes, full resolution; engine/label_motion.py), counted when
    it stands ``motion_sigmas`` uncertainties out and explains ``motion_min_gain`` of the charge.
    No render: the map enters through the reference's depth."""
    assert reference.view is not None
    t0 = time.perf_counter()
    motion = estimate_motion(reference.view, labels, camera)
    moved = Pose.from_matrix(calibrated.rotation @ motion.rotation,
                             calibrated.translation + calibrated.rotation @ motion.translation)
    dt, dr = motion.distance_m, motion.angle_deg
    k = dp.motion_sigmas
    stands_out = dr > k * motion.angle_sigma_deg or dt > k * motion.distance_sigma_m
    counted = stands_out and motion.gain >= dp.motion_min_gain
    what = (f"drift {dt * 100:.1f} cm / {dr:.2f} deg (+- {motion.distance_sigma_m * 100:.1f} cm /"
            f" {motion.angle_sigma_deg:.2f} deg)")
    if motion.cost_after > dp.motion_max_cost:
        level, why = "error", (f"the image no longer matches its reference (boundary charge "
                               f"{motion.cost_after:.2f} > {dp.motion_max_cost:g} after the best "
                               "motion): moved further than the check follows, recalibrate")
        counted = True
    elif counted and (dt > dp.bound_m or dr > dp.bound_deg):
        level, why = "error", (f"{what} beyond the check's bounds ({dp.bound_m * 100:.0f} cm / "
                               f"{dp.bound_deg:g} deg): recalibrate")
    elif counted:
        level, why = graded(what, dt, dr, dp)
    elif not stands_out:
        level, why = "ok", (f"no move beyond its uncertainty since the reference ({what}, "
                            f"< {k:g} x the +-)")
    else:
        level, why = "ok", (f"no clear move since the reference ({what} explains "
                            f"{motion.gain * 100:.0f} % < {dp.motion_min_gain * 100:.0f} % of "
                            "the boundaries' charge)")
    vec_d = moved.translation - calibrated.translation if counted else np.zeros(3)
    return DriftReport(level, why, calibrated, moved, float(dt) if counted else 0.0,
                       float(dr) if counted else 0.0,
                       (float(vec_d[0]), float(vec_d[1]), float(vec_d[2])),
                       float(motion.cost_before), float(motion.cost_after),
                       reference.coverage, motion.evaluations,
                       time.perf_counter() - t0, motion=motion)


class DriftChecker:
    """The drift watch of one camera: its map prepared once (around the calibration), a check per
    label image. ``prepared`` shares a map already prepared with the same label mapping (several
    cameras on one map)."""

    def __init__(self, map_cloud: LabelledCloud, camera: CameraModel, calibrated: Pose,
                 engine: CalibrationParams | None = None, drift: DriftParams | None = None,
                 mapping: LabelMapping | None = None, prepared: PreparedMap | None = None
                 ) -> None:
        self.drift = drift or DriftParams()
        self.params = check_params(engine or CalibrationParams(), self.drift)
        self.mapping = mapping_for(self.params, mapping)
        self.map_cloud, self.camera, self.calibrated = map_cloud, camera, calibrated
        self.pmap = prepared if prepared is not None else prepare_map(
            map_cloud, self.mapping, center=calibrated.translation,
            radius=self.params.render.crop_radius or None)

    def check(self, labels: np.ndarray | None, calibrated: Pose | None = None,
              reference: DriftReport | None = None) -> DriftReport:
        """Check ``calibrated`` (default: the one given at construction) against ``labels``
        (mono8 Cityscapes trainIds; None: no image yet), counted from ``reference`` if given:
        a reference that kept its view measures the camera's motion from its image
        (:func:`check_motion`), otherwise against the map (:func:`check_drift`)."""
        pose = calibrated or self.calibrated
        t0 = time.perf_counter()
        if labels is None:
            return unknown(pose, "no label image yet")
        if reference is not None and reference.view is not None and \
                np.allclose(reference.calibrated.vector(), pose.vector(), atol=1e-9):
            labels = np.asarray(labels)
            if labels.ndim != 2 or labels.dtype != np.uint8 or \
                    labels.shape != reference.view.labels.shape:
                return unknown(pose, f"label image {labels.dtype} {labels.shape} does not fit "
                                     f"the reference's {reference.view.labels.shape}")
            try:
                report = check_motion(reference, self.mapping.map_image(labels), self.camera,
                                      pose, self.drift)
                return replace(report, seconds=time.perf_counter() - t0)
            except ValueError:  # too little in the reference to align: the map decides
                reference = replace(reference, view=None)
        try:
            problem = Problem(self.map_cloud, labels, self.camera, pose.translation,
                              self.params, prepared=self.pmap)
        except ValueError as exc:
            return unknown(pose, str(exc), t0)
        report = check_drift(problem, pose, self.drift, reference)
        return replace(report, seconds=time.perf_counter() - t0)


__all__ = ["DIAGNOSTIC_LEVEL", "LEVELS", "DriftChecker", "DriftParams", "DriftReport",
           "check_drift", "check_params"]
