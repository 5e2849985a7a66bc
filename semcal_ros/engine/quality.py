"""How good is a calibration, without ground truth: the quality report and its verdict.

The loss value means nothing to a user ("the cost is 0.98, what does it mean?"). What they can act
on is whether the map, drawn at the result, agrees with what the camera sees; whether the answer is
pinned down on every axis (a camera looking along a featureless road cannot tell where along the road
it stands); and whether independent starts agreed. :func:`assess` measures these from the problem's
public loss at a pose, so ``semcal calibrate``, the action and the drift watch share one report:

* agreement: share of pixels where the map drew a point and the target has a class whose classes
  agree, overall and per target class;
* coverage: share of the target's scene pixels the map covers;
* per-axis uncertainty: how far each of x, y, z (map frame) and roll, pitch, yaw (camera body) can
  move from the result, alone, before the loss rises by ``rise`` (relative) + ``rise_abs``; the larger
  of the two directions, capped at the search bound (a capped axis is unconstrained). The relative
  rise is measured above the loss's floor at the result (what a perfect match with the same coverage
  would score, :meth:`~semcal_ros.engine.loss.LabelLoss.floor`: 0 for the paper's L2), so a loss
  whose perfect match is not 0 (the likelihood's shrunk confusion matrix) is judged like L2;
* the verification runs: a distinct basin whose refined loss is as low as the result's (within
  ``rival_margin`` of its rise above the floor) means the data cannot decide between two places;
* the start: a result farther from its initial guess than the basin measured on the scene
  catalogue (``basin_*``; yaw not counted when the yaw search ran) came from a start nobody
  measured to converge, so it is not called good (docs/engine.md "How good must the start be").

The verdict: ``failed`` when agreement is below ``min_agreement`` or runs disagree; else
``inconclusive`` when the coverage is below ``min_coverage`` or an axis's uncertainty exceeds
``max_translation_m`` / ``max_rotation_deg`` (the reason names the axis); else ``good``. A start
beyond the measured basin makes a good verdict inconclusive and is named in the reason of every
verdict. The thresholds and how they were chosen on scenes are in docs/quality.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from semcal_ros.engine.labels import CITYSCAPES, INVALID, SKY
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error

from semcal_ros.engine.evidence import Evidence, axis_offsets
from semcal_ros.engine.results import ClassEvidence, QualityReport, RunResult


class ProbedProblem(Protocol):
    """What the report needs of a :class:`~semcal_ros.engine.problem.Problem`: its loss at a pose,
    its render and its settings. A protocol, so that the report depends on no engine module above
    it (the problem imports the parameters, which hold :class:`QualityParams`)."""

    params: Any
    target: Any
    stages: Any

    def loss(self, pose: Pose, stage: int = -1) -> float: ...

    def render(self, pose: Pose, stage: int = -1) -> np.ndarray: ...

    def level(self, stage: int) -> Any: ...  # .loss: evaluate(rendered), floor(rendered)

AXES = ("x", "y", "z", "roll", "pitch", "yaw")
VERDICTS = ("good", "inconclusive", "failed")


@dataclass(frozen=True)
class QualityParams:
    """Thresholds of the verdict (``engine.quality.*``); docs/quality.md says how each was chosen."""

    rise: float = 0.10  # relative loss rise that bounds an axis's uncertainty
    rise_abs: float = 1e-4  # plus this absolute rise (a loss near 0 still has a noise floor)
    step_m: float = 0.01  # first probe along a translation axis; doubled until the loss rises
    step_deg: float = 0.02  # first probe about a rotation axis
    bisections: int = 2  # refinements of each axis's bracket
    stage: int = -1  # schedule stage whose resolution the probes use (-1: full resolution)
    max_translation_m: float = 0.10  # an axis looser than this is unconstrained: inconclusive
    max_rotation_deg: float = 0.2
    min_agreement: float = 0.6  # below: failed (the map is not what the camera sees)
    min_coverage: float = 0.15  # below: inconclusive (too little of the image to judge)
    disagree_translation_m: float = 0.3  # a rival basin this far away with a loss as low: failed
    disagree_rotation_deg: float = 0.3
    rival_margin: float = 0.02  # "as low": refined loss <= best + margin x (best - floor)
    # the start's basin measured on the four catalogue layouts (docs/engine.md "How good must the
    # start be"): a result farther from its start than this (per map axis; body pitch; body yaw,
    # unless the yaw search ran) came from a start no measurement covers: at most inconclusive
    basin_translation_m: float = 2.5
    basin_pitch_deg: float = 5.0
    basin_yaw_deg: float = 5.0
    # the uncertainty from independent evidence (engine/evidence.py): each part's refinement
    # from the result gets this many full-resolution evaluations (0: the loss-rise probes
    # instead), and the reported +- is evidence_sigmas x its sigma per axis
    evidence_evaluations: int = 60
    evidence_sigmas: float = 3.0
    # ... each from an initial simplex of this share of the search bounds (2.5 cm / 0.05 deg):
    # the last stage's 0.03 left the refinements' own scatter in the +- (1.6 against 0.7 cm of
    # sigma on the ideal demo junction, measured from the truth)
    evidence_simplex: float = 0.01
    # with the evidence, a start as low counts as a contradiction (failed) only beyond 3 x the
    # +- and beyond these; nearer, it widens the +- (a KITTI 3-frame result 3.3 cm off had a
    # start 0.11 m / 0.38 deg away as low: the same answer's uncertainty, not a second answer)
    contradict_translation_m: float = 1.0
    contradict_rotation_deg: float = 1.0
    # one label image cannot show a bias all its pixels share (a labeller that calls every
    # facade vegetation moves every strip alike): below trusted_agreement, a single frame's +-
    # is at least the floor its kind was measured off by (docs/quality.md: 90th percentile per
    # axis of 45 real single-frame results of KITTI 00, KITTI object and PJLab)
    trusted_agreement: float = 0.9
    single_frame_floor_m: float = 1.0
    single_frame_floor_deg: float = 2.0

    def __post_init__(self) -> None:
        for name in ("rise", "rise_abs", "min_agreement", "min_coverage", "rival_margin",
                     "trusted_agreement", "single_frame_floor_m", "single_frame_floor_deg",
                     "contradict_translation_m", "contradict_rotation_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"quality.{name} must be a finite number >= 0, got {value}")
        for name in ("step_m", "step_deg", "max_translation_m", "max_rotation_deg",
                     "disagree_translation_m", "disagree_rotation_deg", "basin_translation_m",
                     "basin_pitch_deg", "basin_yaw_deg", "evidence_sigmas"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"quality.{name} must be a finite number > 0, got {value}")
        if int(self.evidence_evaluations) != self.evidence_evaluations or \
                self.evidence_evaluations < 0:
            raise ValueError(f"quality.evidence_evaluations must be an integer >= 0, got "
                             f"{self.evidence_evaluations}")
        if not (math.isfinite(self.evidence_simplex) and 0 < self.evidence_simplex <= 1):
            raise ValueError(f"quality.evidence_simplex must be in (0, 1], got "
                             f"{self.evidence_simplex}")
        if self.bisections < 0:
            raise ValueError(f"quality.bisections must be >= 0, got {self.bisections}")
        if not (self.min_agreement <= 1 and self.min_coverage <= 1):
            raise ValueError("quality.min_agreement and quality.min_coverage are shares in [0, 1]")


def label_agreement(rendered: np.ndarray, target: np.ndarray, crop_top: float = 0.0
                    ) -> tuple[float, dict[str, float]]:
    """Share of pixels where the map drew a point and the target has a class whose classes agree,
    and the same per target class (by Cityscapes name; not sky: the map has no sky to draw, so
    it could only disagree), in class order. Both images hold aligned classes."""
    return (_overall_agreement(rendered, target, crop_top),
            _agreement_per_class(_classes_in_order(rendered, target, crop_top)))


def class_evidence(rendered: np.ndarray, target: np.ndarray, crop_top: float = 0.0
                   ) -> tuple[ClassEvidence, ...]:
    """Per class of the labels (not sky), largest first: its share of the labelled pixels, the
    share of its pixels a map point covers, and the share of those the map labels the same.
    Both images hold aligned classes."""
    return _largest_first(_classes_in_order(rendered, target, crop_top))


def _overall_agreement(rendered: np.ndarray, target: np.ndarray, crop_top: float) -> float:
    top = int(round(crop_top * target.shape[0]))
    r, t = rendered[top:].ravel(), target[top:].ravel()
    both = (r != INVALID) & (t != INVALID)
    return float((r[both] == t[both]).mean()) if both.any() else 0.0


def _classes_in_order(rendered: np.ndarray, target: np.ndarray, crop_top: float
                      ) -> list[ClassEvidence]:
    """:func:`class_evidence`'s figures in class order: the one count behind the per-class
    agreement and the per-class evidence."""
    top = int(round(crop_top * target.shape[0]))
    r = rendered[top:].ravel()
    t = target[top:].ravel()
    labelled = (t != INVALID) & (t != SKY)
    if not labelled.any():
        return []
    t, r = t[labelled], r[labelled]
    total = np.bincount(t, minlength=256)
    drawn = r != INVALID
    covered = np.bincount(t[drawn], minlength=256)
    same = np.bincount(t[drawn & (r == t)], minlength=256)
    return [ClassEvidence(CITYSCAPES.get(int(c), str(int(c))), float(total[c] / len(t)),
                          float(covered[c] / total[c]),
                          float(same[c] / covered[c]) if covered[c] else 0.0)
            for c in np.nonzero(total)[0]]


def _agreement_per_class(classes: list[ClassEvidence]) -> dict[str, float]:
    """The agreement of each class the map covers (the report's ``agreement_per_class``)."""
    return {c.name: c.agreement for c in classes if c.coverage > 0}


def _largest_first(classes: list[ClassEvidence]) -> tuple[ClassEvidence, ...]:
    return tuple(sorted(classes, key=lambda e: -e.share))


def axis_uncertainty(problem: ProbedProblem, pose: Pose, params: QualityParams,
                     bounds: Sequence[float], on_probe: Callable[[], None] | None = None,
                     loss0: float | None = None, floor0: float | None = None
                     ) -> tuple[np.ndarray, int]:
    """Per axis (x, y, z in m; roll, pitch, yaw in deg): how far the pose can move along it, in
    either direction, before the loss at ``params.stage`` rises by the set amount. Probes double
    from ``step`` until the loss rises or the bound is passed, then bisect the bracket; the larger
    direction counts. Returns the six values and the evaluations spent. ``on_probe`` is called
    before every probe (the search's cancellation check raises from it); ``loss0``, the loss at
    ``pose`` at the probes' stage and ``floor0`` its floor, when the caller has them already.
    The loss must rise by ``rise`` times its excess over the floor (plus ``rise_abs``)."""
    base = pose.vector()
    spent = 0
    if loss0 is None or floor0 is None:
        rendered = problem.render(pose, params.stage)
        loss0, _ = problem.level(params.stage).loss.evaluate(rendered)
        floor0, spent = problem.level(params.stage).loss.floor(rendered), 1
    limit = floor0 + (loss0 - floor0) * (1.0 + params.rise) + params.rise_abs
    out = np.zeros(6)
    for axis in range(6):
        rotation = axis >= 3
        step = math.radians(params.step_deg) if rotation else params.step_m
        bound = math.radians(bounds[axis]) if rotation else bounds[axis]
        worst = 0.0
        for sign in (1.0, -1.0):
            def rises(d: float) -> bool:
                if on_probe is not None:
                    on_probe()
                v = base.copy()
                v[axis] += sign * d
                return problem.loss(Pose.from_vector(v), params.stage) > limit

            inside, d = 0.0, step
            while d < bound:
                spent += 1
                if rises(d):
                    break
                inside, d = d, d * 2.0
            else:
                worst = bound
                break
            lo, hi = inside, d
            for _ in range(params.bisections):
                mid = 0.5 * (lo + hi)
                spent += 1
                if rises(mid):
                    hi = mid
                else:
                    lo = mid
            worst = max(worst, hi)
        out[axis] = math.degrees(worst) if rotation else worst
    return out, spent


def start_offset(start: Pose, result: Pose) -> tuple[float, float, float]:
    """How far the result lies from its start, as the basin was measured: the largest map-axis
    translation difference (m; starts were drawn per axis), the body pitch and the body yaw
    difference (deg, yaw wrapped to [0, 180])."""
    dt = float(np.max(np.abs(result.translation - start.translation)))
    d = result.body_rpy_deg() - start.body_rpy_deg()
    return dt, float(abs(d[1])), float(abs((d[2] + 180.0) % 360.0 - 180.0))


def beyond_basin(offset: tuple[float, float, float], params: QualityParams, yaw_searched: bool
                 ) -> str:
    """The reason text when ``offset`` (:func:`start_offset`) lies beyond the measured basin, or
    "" inside it. The yaw is not judged when the yaw search covered the full circle."""
    dt, dp, dy = offset
    over = dt > params.basin_translation_m or dp > params.basin_pitch_deg or \
        (not yaw_searched and dy > params.basin_yaw_deg)
    if not over:
        return ""
    yaw_bound = "any yaw (yaw search)" if yaw_searched else f"{params.basin_yaw_deg:g} deg yaw"
    return (f"the start was {dt:.1f} m / {dy:.0f} deg yaw / {dp:.1f} deg pitch from the result, "
            f"beyond the measured basin ({params.basin_translation_m:g} m per axis, {yaw_bound}, "
            f"{params.basin_pitch_deg:g} deg pitch): check the start")


def assess(problem: ProbedProblem, pose: Pose, runs: Sequence["RunResult"] = (),
           params: QualityParams | None = None,
           on_probe: Callable[[], None] | None = None, start: Pose | None = None,
           evidence: Evidence | None = None, at_bounds: bool = False) -> QualityReport:
    """The quality report of ``pose`` on ``problem`` (see the module docstring). ``runs`` are the
    verification runs of the calibration (empty for a pose from elsewhere, e.g. a drift check);
    ``start`` its initial guess, judged against the measured basin (None: not judged);
    ``evidence`` the result refined on independent parts (engine/evidence.py): its sigma, x
    ``evidence_sigmas``, is the uncertainty (None: the loss-rise probes measure it);
    ``at_bounds``: the search ended at a face of its box (the answer may lie beyond)."""
    qp = params or problem.params.quality
    sp = problem.params.search
    rendered = problem.render(pose)  # one full-resolution render serves agreement and loss
    crop = problem.params.loss.crop_top
    agreement = _overall_agreement(rendered, problem.target, crop)
    in_order = _classes_in_order(rendered, problem.target, crop)
    per_class = _agreement_per_class(in_order)
    loss_full, coverage = problem.level(-1).loss.evaluate(rendered)
    floor_full = problem.level(-1).loss.floor(rendered)
    at_full = problem.stages[qp.stage].scale == problem.stages[-1].scale
    bounds = (*sp.bound_xyz, sp.bound_roll_deg, sp.bound_pitch_deg, sp.bound_yaw_deg)
    # verification runs: spread of the agreeing ones; the refined runs whose loss is as low
    best = [r for r in runs if r.basin == 0]
    dt = [translation_error(r.pose, pose) for r in best]
    dr = [rotation_error_deg(r.pose, pose) for r in best]
    loss_best = min((r.loss for r in runs if r.refined), default=math.inf)
    as_low = [r for r in runs if r.refined
              and r.loss <= loss_best + qp.rival_margin * max(loss_best - floor_full, 0.0)]
    far = [r for r in as_low if r.basin != 0 and (
        translation_error(r.pose, pose) > qp.disagree_translation_m
        or rotation_error_deg(r.pose, pose) > qp.disagree_rotation_deg)]
    cap = np.array(bounds, float)
    contradicted: list = []
    note = ""
    if evidence is not None:
        # the independent evidence's +-, never below the refinements' own resolution (half
        # their initial simplex: parts that all stayed at the result say it is within that, not
        # that it is exact), widened to every start that ended as low: those the evidence
        # allows (within 3 x its +-) are the same answer's uncertainty; one beyond is a second
        # answer the data supports as well: contradicted
        sigma = np.maximum(evidence.sigma, 0.5 * qp.evidence_simplex * cap)
        if not sp.free_roll:
            sigma[3] = 0.0
        unc = np.minimum(qp.evidence_sigmas * sigma, cap)
        if evidence.frames == 1 and agreement < qp.trusted_agreement:
            floor = np.array([qp.single_frame_floor_m] * 3 + [qp.single_frame_floor_deg] * 3)
            unc = np.maximum(unc, np.minimum(floor, cap))
            note = (f"; one label image whose labels disagree with the map on "
                    f"{(1 - agreement) * 100:.0f} % of the pixels cannot show a bias they all "
                    "share: calibrate 3 or more frames together")
        reach = max(3.0 * float(np.linalg.norm(unc[:3])), qp.contradict_translation_m)
        reach_deg = max(3.0 * float(np.linalg.norm(unc[3:])), qp.contradict_rotation_deg)
        contradicted = [r for r in far if translation_error(r.pose, pose) > reach
                        or rotation_error_deg(r.pose, pose) > reach_deg]
        for r in as_low:
            unc = np.maximum(unc, np.minimum(np.abs(axis_offsets(r.pose, pose)), cap))
        spent = 0
    else:
        unc, spent = axis_uncertainty(problem, pose, qp, bounds, on_probe,
                                      loss_full if at_full else None,
                                      floor_full if at_full else None)
        contradicted = far
    loose = tuple(AXES[i] for i in range(6)
                  if unc[i] > (qp.max_translation_m if i < 3 else qp.max_rotation_deg))
    if not sp.free_roll:
        loose = tuple(a for a in loose if a != "roll")  # held fixed: not the search's to pin down
    failure = ""
    if agreement < qp.min_agreement:
        failure = (f"labels agree on {agreement * 100:.0f} % of the pixels (< "
                   f"{qp.min_agreement * 100:.0f} %): the map is not what the camera sees from "
                   "here")
    elif at_bounds:
        failure = "the result lies at the bounds of its start's prior: the answer may lie beyond"
    elif contradicted:
        r = min(contradicted, key=lambda run: run.loss)
        failure = (f"runs disagree: a start ended {translation_error(r.pose, pose):.2f} m / "
                   f"{rotation_error_deg(r.pose, pose):.2f} deg away with a loss as low")
    if failure:
        verdict, reason = "failed", failure
        if evidence is not None:  # a failed result says no more than the prior: its bounds
            unc = np.where(np.arange(6) == 3, unc, cap) if not sp.free_roll else cap.copy()
            loose = tuple(a for a in AXES if a != "roll" or sp.free_roll)
    elif coverage < qp.min_coverage:
        verdict, reason = "inconclusive", (f"the map covers {coverage * 100:.0f} % of the image "
                                           f"(< {qp.min_coverage * 100:.0f} %)")
    elif loose:
        parts = [f"{a} +-{unc[AXES.index(a)] * (100 if AXES.index(a) < 3 else 1):.3g} "
                 f"{'cm' if AXES.index(a) < 3 else 'deg'}" for a in loose]
        more = note or ("; more frames would narrow it" if evidence is not None else "")
        verdict, reason = "inconclusive", "unconstrained: " + ", ".join(parts) + more
    else:
        verdict, reason = "good", ("every axis pinned down by independent evidence, labels agree"
                                   if evidence is not None else
                                   "every axis pinned down, labels agree")
    offset = start_offset(start, pose) if start is not None else None
    outside = beyond_basin(offset, qp, sp.yaw_search) if offset is not None else ""
    if outside:
        # a good verdict from an unmeasured start is not trusted; any verdict names the start
        was_good = verdict == "good"
        verdict = "inconclusive" if was_good else verdict
        reason = outside if was_good else f"{reason}; {outside}"
    return QualityReport(
        verdict=verdict, reason=reason, agreement=agreement, agreement_per_class=per_class,
        coverage=coverage,
        uncertainty_translation_m=(float(unc[0]), float(unc[1]), float(unc[2])),
        uncertainty_rpy_deg=(float(unc[3]), float(unc[4]), float(unc[5])), unconstrained=loose,
        spread_translation_m=float(np.sqrt(np.mean(np.square(dt)))) if dt else 0.0,
        spread_rotation_deg=float(np.sqrt(np.mean(np.square(dr)))) if dr else 0.0,
        evaluations=spent + 1, roll_free=sp.free_roll, start_offset=offset,
        start_outside_basin=bool(outside),
        uncertainty_method=evidence.method if evidence is not None else "loss rise",
        evidence_sigma=tuple(float(v) for v in evidence.sigma) if evidence is not None else (),
        evidence_moves=tuple(float(v) for v in evidence.moves) if evidence is not None else (),
        classes=_largest_first(in_order))


__all__ = ["AXES", "VERDICTS", "QualityParams", "QualityReport", "assess", "axis_uncertainty",
           "beyond_basin", "class_evidence", "label_agreement", "start_offset"]
