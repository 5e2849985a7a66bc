"""The search: Nelder-Mead over the camera pose, coarse to fine, from several starts.

``calibrate`` is the paper's whole procedure in one call: the map is prepared once (a
:class:`~semcal_ros.engine.problem.Problem`), then :func:`solve` runs

1. the first, coarse stage (quarter resolution, thinned far points) from the initial guess and from
   ``verification.starts`` perturbed guesses (the paper's verification runs);
2. merges starts that ended in the same place (one basin) and ranks the basins by coarse loss;
3. refines the best basin, and any distinct basin whose coarse loss is within
   ``verification.refine_margin`` of it, through the finer stages and the paper's restarts of the
   last stage (at most ``refine_max``);
4. returns the refined pose of lowest full-resolution loss, with how many starts agreed on it.

Full-resolution renders cost ten times a coarse one, so they are spent only where they can change
the answer; docs/engine.md has the measurements behind each choice.
"""

from __future__ import annotations

import copy
import threading
import time
from typing import Callable

import numpy as np
from scipy.optimize import minimize

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.evidence import Evidence, evidence_uncertainty
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.quality import QualityParams, assess
from semcal_ros.engine.results import CalibrationResult, Progress, RunResult
from semcal_ros.engine.workers import side_by_side
from semcal_ros.errors import CalibrationFailed, Cancelled, InputError  # Cancelled: raised here


class _Stalled(Exception):
    """Ends a Nelder-Mead stage whose best loss stopped improving (see Search.nelder_mead)."""


class EvaluationCounter:
    """Counts evaluations, records history, reports progress, honours cancellation. Searches
    run side by side each count on a :meth:`fork` (their own history, the progress through this
    one), joined in a fixed order by :meth:`join`: the history does not depend on which thread
    ran first."""

    def __init__(self, progress: Callable[[Progress], None] | None,
                 should_stop: Callable[[], bool] | None, interval: float = 0.25) -> None:
        self.progress, self.should_stop, self.interval = progress, should_stop, interval
        self.evaluations = 0
        self.history: list[tuple[int, int, float]] = []
        self.stage = "start"
        self._best: tuple[float, Pose] | None = None
        self._last_report = 0.0
        self._parent: EvaluationCounter | None = None
        self._forked = 0  # evaluations of forks not yet joined (for the progress reports)
        self._lock = threading.Lock()

    def fork(self) -> "EvaluationCounter":
        child = EvaluationCounter(None, self.should_stop, self.interval)
        child._parent = self
        return child

    def join(self, forks: list["EvaluationCounter"]) -> None:
        """Take the forks' evaluations and history, in the order given."""
        with self._lock:
            for f in forks:
                self.evaluations += f.evaluations
                self._forked -= f.evaluations
                self.history.extend(f.history)

    def check(self) -> None:
        """Raise :class:`Cancelled` when the caller asked to stop."""
        if self.should_stop is not None and self.should_stop():
            raise Cancelled("calibration cancelled")

    def begin_stage(self, name: str) -> None:
        if self._parent is None:  # a fork's stages are its parent's to name
            self.stage, self._best = name, None

    def record(self, run: int, stage: int, loss: float, pose: Pose) -> None:
        self.check()
        self.history.append((run, stage, loss))
        if self._parent is None:
            self._observe(loss, pose, 1, 0)
        else:
            self.evaluations += 1
            self._parent._observe(loss, pose, 0, 1)

    def _observe(self, loss: float, pose: Pose, own: int, forked: int) -> None:
        with self._lock:
            self.evaluations += own
            self._forked += forked
            if self._best is None or loss < self._best[0]:
                self._best = (loss, pose)
            now = time.monotonic()
            if now - self._last_report < self.interval:
                return
            self._last_report = now
        self.report()

    def report(self) -> None:
        if self.progress is not None and self._best is not None:
            self.progress(Progress(self.stage, self.evaluations + self._forked,
                                   float(self._best[0]), self._best[1]))


class Search:
    """Nelder-Mead on one problem, in units of the search bounds around a centre pose."""

    def __init__(self, problem: Problem, counter: EvaluationCounter) -> None:
        self.problem, self.counter = problem, counter
        sp = problem.params.search
        # free parameters (x, y, z, [roll], pitch, yaw) and their search bounds
        self.free = np.array([0, 1, 2] + ([3] if sp.free_roll else []) + [4, 5])
        bounds = np.array([*sp.bound_xyz, np.radians(sp.bound_roll_deg),
                           np.radians(sp.bound_pitch_deg), np.radians(sp.bound_yaw_deg)])
        self.scale = bounds[self.free]
        # (centre vector, half-widths of x, y, z, roll, pitch, yaw): poses outside cost the
        # degenerate loss without a render (None: unconfined); see confine()
        self.box: tuple[np.ndarray, np.ndarray] | None = None
        # > 0: the loss plus this x the share of the labels' scene the map leaves uncovered (the
        # yaw search: near-empty views otherwise score a loss near 0); see score()
        self.coverage_weight = 0.0

    def forked(self) -> "Search":
        """This search (problem, bounds, weights) counting on a fork of its counter: one of
        several run side by side (engine/workers.py)."""
        other = copy.copy(self)
        other.counter = self.counter.fork()
        return other

    def confine(self, initial: Pose, factor: float = 1.0, yaw: bool = True) -> None:
        """Keep the search within ``factor`` x the bounds of ``initial`` on every free axis
        (yaw only with ``yaw``): the bounds are the prior the caller gave, and a result outside
        them is a different answer to a different question. Unconfined, runs from the paper's
        starts on real labels ended 9.3 m / 11.6 deg and 3.6 m / 18.8 deg from their starts, in
        views that hide the map's disagreements. With the heading unknown (the yaw search, x 1.5,
        yaw free), coarse runs from wrong headings otherwise wander 10-30 m off into views that
        show little of the map (docs/engine.md "How good must the start be")."""
        if factor <= 0:
            self.box = None
            return
        sp = self.problem.params.search
        inf = np.inf
        half = np.array([*sp.bound_xyz,
                         np.radians(sp.bound_roll_deg) if sp.free_roll else inf,
                         np.radians(sp.bound_pitch_deg),
                         np.radians(sp.bound_yaw_deg) if yaw else inf]) * factor
        self.box = (initial.vector(), half)

    def at_face(self, v: np.ndarray, loss: float, share: float = 0.98) -> bool:
        """``v`` lies within (1 - ``share``) of a face of the box on an axis the box holds, and
        the loss just beyond that face (2 % of the bound further out) is lower than ``loss``:
        the search was held back by its bounds. A result merely near a face is not: the paper's
        starts lie up to the whole prior from the truth, so the truth itself can be there."""
        if self.box is None:
            return False
        centre, half = self.box
        offset = box_offset(v, centre)
        for k in np.nonzero(np.isfinite(half) & (half > 0) & (offset > share * half))[0]:
            out = np.array(v, float)
            d = out[k] - centre[k]
            if k >= 3:
                d = (d + np.pi) % (2 * np.pi) - np.pi
            out[k] += np.sign(d) * 0.02 * half[k]
            if self.problem.loss(Pose.from_vector(out)) < loss:
                return True
        return False

    def score(self, pose: Pose, stage: int) -> float:
        """What the search minimises: the problem's loss, or the degenerate loss outside the box,
        plus ``coverage_weight`` x the uncovered share of the labels' scene when set."""
        if self.outside(pose.vector()):
            return float(self.problem.params.loss.degenerate_loss)
        if self.coverage_weight <= 0:
            return self.problem.loss(pose, stage)
        e = self.problem.evaluate(pose, stage)
        return e.loss + self.coverage_weight * (1.0 - e.coverage)

    def outside(self, v: np.ndarray) -> bool:
        if self.box is None:
            return False
        return bool(np.any(box_offset(v, self.box[0]) > self.box[1] * (1.0 + 1e-9)))

    def pose_at(self, center: np.ndarray, s: np.ndarray) -> Pose:
        v = np.array(center, dtype=float)
        v[self.free] += self.scale * s
        return Pose.from_vector(v)

    def nelder_mead(self, stage: int, center: np.ndarray, run: int,
                    max_evaluations: int | None = None, simplex: float | None = None
                    ) -> tuple[np.ndarray, float]:
        """One Nelder-Mead search of ``stage`` around ``center``: the best pose it evaluated
        (not its last simplex vertex) and that pose's loss. ``max_evaluations`` replaces the
        stage's cap (the yaw search's short probes), ``simplex`` the stage's initial simplex
        (a share of the bounds)."""
        st = self.problem.stages[stage]
        cap = st.max_evaluations if max_evaluations is None else max_evaluations
        best: list = [np.inf, center]
        # the loss is piecewise constant in the pose: near its end a stage wanders on plateaus
        # until the simplex has shrunk below xatol, renders that cannot change the answer. It
        # ends instead once its best loss has not dropped by more than fatol for this many
        # evaluations (0: off, scipy's own tests only)
        stall = self.problem.params.schedule.stall_evaluations
        mark = [np.inf, 0]  # the best loss at the last real improvement, evaluations since

        def objective(s: np.ndarray) -> float:
            pose = self.pose_at(center, s)
            value = self.score(pose, stage)
            self.counter.record(run, stage, value, pose)
            if value < best[0]:
                best[0], best[1] = value, pose.vector()
            if value < mark[0] - st.fatol:
                mark[0], mark[1] = value, 0
            else:
                mark[1] += 1
                if stall and mark[1] >= stall:
                    raise _Stalled
            return value

        n = len(self.free)
        try:
            minimize(objective, np.zeros(n), method="Nelder-Mead",
                     options={"initial_simplex": _initial_simplex(n) * (
                                  st.simplex if simplex is None else simplex),
                              "xatol": self.problem.params.schedule.xatol, "fatol": st.fatol,
                              "maxfev": cap})
        except _Stalled:
            pass
        if self.outside(best[1]) and not self.outside(center):
            # the simplex is centred on ``center`` and never evaluates it: from the edge of the
            # box every vertex may lie outside; the centre then stays the answer
            pose = Pose.from_vector(center)
            return pose.vector(), float(self.score(pose, stage))
        return best[1], float(best[0])

    def coarse(self, start: Pose, run: int, label: str) -> tuple[np.ndarray, float]:
        self.counter.begin_stage(f"{label}, stage 1/{len(self.problem.stages)} "
                                 f"(1/{self.problem.stages[0].scale} resolution)")
        return self.nelder_mead(0, start.vector(), run)

    def restart(self, stage: int, center: np.ndarray, loss: float, run: int, label: str
                ) -> tuple[np.ndarray, float]:
        """The paper's restarts: ``stage`` again from its own result while that still lowers
        the loss by more than the stage's tolerance."""
        st = self.problem.stages[stage]
        for r in range(st.restarts):
            self.counter.begin_stage(f"{label}, stage {stage + 1}/{len(self.problem.stages)}, "
                                     f"restart {r + 1}")
            moved, after = self.nelder_mead(stage, center, run)
            improved = loss - after
            if after < loss:
                center, loss = moved, after
            if improved <= st.fatol:
                break
        return center, loss

    def refine(self, center: np.ndarray, loss: float, run: int, label: str,
               restart_first: bool = True, first: int = 1, last: int = -1
               ) -> tuple[np.ndarray, float]:
        """From a coarse result: the first stage's restarts (unless ``restart_first`` is False),
        then the stages ``first`` to ``last`` (default: every later one) and their restarts.
        The loss returned is the last stage's."""
        stages = self.problem.stages
        last = last % len(stages)
        em = self.problem.params.loss.em
        if restart_first:
            center, loss = self.restart(0, center, loss, run, label)
        for k in range(first, last + 1):
            self.counter.begin_stage(f"{label}, stage {k + 1}/{len(stages)} "
                                     f"(1/{stages[k].scale} resolution)")
            if em:  # E step at the stage's start, then the stage minimises under it
                self.problem.freeze(Pose.from_vector(center), k)
            center, loss = self.nelder_mead(k, center, run)
            center, loss = self.restart(k, center, loss, run, label)
        if em:  # results are compared under the loss re-estimated at each pose
            self.problem.thaw()
            loss = self.score(Pose.from_vector(center), last)
        return center, loss


def box_offset(v: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """|v - centre| per pose-vector axis (x, y, z, roll, pitch, yaw), angles wrapped to pi."""
    d = np.asarray(v, float) - np.asarray(centre, float)
    d[3:] = (d[3:] + np.pi) % (2 * np.pi) - np.pi
    return np.abs(d)


def _initial_simplex(n: int) -> np.ndarray:
    """n+1 vertices centred on the origin reaching +1 in every coordinate: the paper builds the
    simplex by adding and subtracting the full parameter range around the initial guess."""
    vertices = np.vstack([np.zeros(n), np.eye(n)])
    vertices -= vertices.mean(axis=0)
    return vertices / vertices.max(axis=0)


def _yaw_candidates(search: Search, initial: Pose) -> list[Pose]:
    """The heading search: every ``yaw_search_step_deg`` over the full circle scored at the
    initial position (one coarse render each); the ``yaw_search_probe`` best get a short coarse
    descent (``yaw_search_probe_evaluations``), and the ``yaw_search_keep`` lowest after it are
    returned, each where its descent ended. Why a descent: scored at the raw start, 2.5-3.5 m off
    the truth, the true heading ranked 0-15th of 36 on the catalogue; once the position has moved
    the right heading's loss drops below the others' (docs/engine.md)."""
    sp = search.problem.params.search
    v = initial.vector()
    scored = []
    search.counter.begin_stage("yaw grid search")
    for yaw in np.arange(-180.0, 180.0, sp.yaw_search_step_deg):
        cand = v.copy()
        cand[5] = v[5] + np.radians(yaw)
        pose = Pose.from_vector(cand)
        value = search.score(pose, 0)
        search.counter.record(-1, 0, value, pose)
        scored.append((value, float(yaw), pose))
    scored.sort(key=lambda item: item[0])
    probed = []
    for k, (_, yaw, pose) in enumerate(scored[: sp.yaw_search_probe]):
        search.counter.begin_stage(f"yaw search: heading {yaw:+.0f} deg "
                                   f"({k + 1}/{min(sp.yaw_search_probe, len(scored))})")
        vec, loss = search.nelder_mead(0, pose.vector(), -1, sp.yaw_search_probe_evaluations)
        probed.append((loss, k, Pose.from_vector(vec)))
    probed.sort(key=lambda item: item[:2])
    return [pose for _, _, pose in probed[: sp.yaw_search_keep]]


def _basins(poses: list[Pose], losses: list[float], tol_m: float, tol_deg: float
            ) -> tuple[list[int], list[int]]:
    """Basin index per start, and the start that heads each basin: greedily, in order of loss,
    a start joins the first better head within (``tol_m``, ``tol_deg``), else heads a basin of
    its own. Basins are numbered in order of their heads' losses."""
    order = np.argsort(losses, kind="stable")
    basin = [-1] * len(poses)
    heads: list[int] = []
    for i in order:
        for b, h in enumerate(heads):
            if translation_error(poses[i], poses[h]) <= tol_m and \
                    rotation_error_deg(poses[i], poses[h]) <= tol_deg:
                basin[i] = b
                break
        else:
            basin[i] = len(heads)
            heads.append(int(i))
    return basin, heads


def _without_label_outliers(problem: Problem, search: Search, pose: Pose, loss: float, run: int
                            ) -> tuple[Pose, float]:
    """Leave out the regions the result says are label errors (``loss.outlier_width_px``) and
    refine again from the result at the finer stages; keeps the first result when nothing is
    left out. The loss returned is the full problem's at the new pose (comparable with the
    runs' losses)."""
    from semcal_ros.engine.loss import label_outliers

    ignore = label_outliers(problem.render(pose), problem.target,
                            problem.params.loss.outlier_width_px)
    if not ignore.any():
        return pose, loss
    masked = Search(problem.masked(ignore), search.counter)
    masked.box = search.box
    center, _ = masked.refine(
        pose.vector(), loss, run, f"without label errors ({ignore.mean() * 100:.1f} % of the "
        "image)", restart_first=False)
    new = Pose.from_vector(center)
    return new, problem.loss(new)


def _refined(problem: Problem, search: Search, basins: list[tuple[int, Pose, float]]
             ) -> tuple[dict[int, tuple[Pose, float, int]], dict[int, tuple[Pose, float, int]]]:
    """The chosen basins refined: (pose, full-resolution loss, evaluations) by run index, those
    taken through every stage and those left before the last.

    Every basin runs the stages up to the one before the last; the last (full resolution, the
    dearest) only the ``verification.refine_final`` best of them by that stage's loss. Each of
    the others is then scored at full resolution where its refinement stopped, and finished as
    well when that score comes within ``refine_margin`` of the finished best (the margin that
    chose the basins for refinement, far wider than the quality report's rival margin): a
    basin that could rival the result, or win, is always finished, so the verdict's count of
    rivals is the same as with every basin finished. One that stopped within the quality
    report's ``disagree_*`` distance of a finished one is not finished and is reported as not
    refined: it can be no rival, and the last stage (its simplex 3 % of the bounds) draws such
    a start to the same place."""
    counter, vp, qp = search.counter, problem.params.verification, problem.params.quality
    last = len(problem.stages) - 1
    n = len(basins)
    n_final = n if vp.refine_final == 0 else min(vp.refine_final, n)
    through = last if n_final == n else last - 1
    labels = {i: f"refining basin {j + 1}/{n}" for j, (i, _, _) in enumerate(basins)}
    # the basins' stages up to ``through`` do not depend on each other: side by side on the
    # workers, each on a fork of the search and, with several, a detached copy of the problem
    # (each holds its own E step)
    forks = [search.forked() for _ in basins]
    if n > 1:
        for fork in forks:
            fork.problem = problem.detached()

    def through_stage(k: int) -> tuple[np.ndarray, float]:
        i, pose, loss = basins[k]
        return forks[k].refine(pose.vector(), loss, i, labels[i], last=through)

    counter.begin_stage(f"refining {n} basin{'s' if n > 1 else ''}")
    refined = side_by_side(through_stage, range(n))
    counter.join([f.counter for f in forks])
    part = {i: refined[k] for k, (i, _, _) in enumerate(basins)}
    spent = {i: forks[k].counter.evaluations for k, (i, _, _) in enumerate(basins)}
    done: dict[int, tuple[Pose, float, int]] = {}

    def finish(i: int) -> None:
        e0 = counter.evaluations
        vec, loss = search.refine(part[i][0], part[i][1], i, labels[i], restart_first=False,
                                  first=last)
        done[i] = (Pose.from_vector(vec), loss, spent[i] + counter.evaluations - e0)

    if through == last:
        return {i: (Pose.from_vector(v), loss, spent[i]) for i, (v, loss) in part.items()}, {}
    for i in sorted(part, key=lambda i: part[i][1])[:n_final]:
        finish(i)
    waiting = {}
    for i in part:
        if i not in done:
            pose = Pose.from_vector(part[i][0])
            waiting[i] = search.score(pose, last)
            counter.record(i, last, waiting[i], pose)
    while waiting:
        reach = min(d[1] for d in done.values()) * (1.0 + vp.refine_margin) + vp.loss_margin_abs
        near = [i for i in waiting if waiting[i] <= reach and not any(
            _agrees(Pose.from_vector(part[i][0]), d[0], qp) for d in done.values())]
        if not near:
            break
        for i in near:
            finish(i)
            del waiting[i]
    rest = {i: (Pose.from_vector(part[i][0]), loss, spent[i] + 1) for i, loss in waiting.items()}
    return done, rest


def _agrees(a: Pose, b: Pose, qp: QualityParams) -> bool:
    """Within the distance under which the quality report counts no rival."""
    return (translation_error(a, b) <= qp.disagree_translation_m
            and rotation_error_deg(a, b) <= qp.disagree_rotation_deg)


def _evidence(problem: Problem, search: Search, pose: Pose) -> Evidence | None:
    """The result refined again on independent parts of its evidence (engine/evidence.py), each
    from the result at full resolution within the search's bounds, ``evidence_evaluations``
    renders each; None when that is 0 (the loss-rise probes measure the uncertainty)."""
    qp = problem.params.quality
    if qp.evidence_evaluations <= 0:
        return None
    last = len(problem.stages) - 1

    em = problem.params.loss.em

    def refine(part: Problem, start: np.ndarray, alone: Search, hold: bool) -> np.ndarray:
        alone.problem = part
        if hold:  # the part minimises what the last stage did: the loss held at its start
            part.freeze(Pose.from_vector(start), last)
        vec, loss = alone.nelder_mead(last, start, 0, max_evaluations=qp.evidence_evaluations,
                                      simplex=qp.evidence_simplex)
        # the simplex never evaluates its centre: the result itself stays the part's answer
        # unless a vertex beat it
        better = loss < alone.score(Pose.from_vector(start), last)
        if hold:
            part.thaw()
        return vec if better else start

    def refine_parts(parts: list[Problem], start: np.ndarray, shared: bool) -> list[np.ndarray]:
        # side by side on the workers, each counting on a fork. Parts made of the problem's own
        # frames would each take the same E step (a frame's, at the same pose): taken once here
        # for every frame, held while they run, instead of by each part in turn
        forks = [search.forked() for _ in parts]
        if em and shared:
            problem.freeze(Pose.from_vector(start), last)
        try:
            vectors = side_by_side(lambda job: refine(job[0], start, job[1], em and not shared),
                                   list(zip(parts, forks)))
        finally:
            if em and shared:
                problem.thaw()
        search.counter.join([f.counter for f in forks])
        return vectors

    search.counter.begin_stage("uncertainty from independent evidence")
    return evidence_uncertainty(problem, pose, refine_parts)


def solve(problem: Problem, initial: Pose, seed: int | None = None,
          progress: Callable[[Progress], None] | None = None,
          should_stop: Callable[[], bool] | None = None) -> CalibrationResult:
    """The full procedure on a prepared problem (see the module docstring)."""
    t0 = time.perf_counter()
    params = problem.params
    counter = EvaluationCounter(progress, should_stop)
    search = Search(problem, counter)
    if not params.search.yaw_search and \
            problem.evaluate(initial, 0).coverage < params.loss.min_coverage:
        raise InputError("no map point in view at the initial pose (check the initial pose, "
                         "its frame and the map)")
    vp = params.verification
    if params.search.yaw_search:
        search.confine(initial, params.search.yaw_search_confine, yaw=False)
        search.coverage_weight = params.search.yaw_search_coverage_weight
        starts = _yaw_candidates(search, initial)
    else:
        search.confine(initial)  # the result stays within the bounds of its start
        starts = [initial]
    # verification starts: around the initial guess; with the yaw search around the kept
    # headings, half of them around the best (a right heading's first descent can stop 1-4 m short)
    kept = list(starts)
    centres = [kept[0] if k % 2 == 0 or len(kept) == 1 else kept[1 + (k // 2) % (len(kept) - 1)]
               for k in range(vp.starts)]
    rng = np.random.default_rng(seed)
    for centre in centres:
        starts.append(search.pose_at(centre.vector(), rng.uniform(-1.0, 1.0, len(search.free))
                                     * min(vp.noise, 1.0)))
    n = len(starts)
    # the starts' coarse stages do not depend on each other: side by side on the workers, each
    # counting on a fork (the same results and history as one after another)
    counter.begin_stage(f"{n} starts, stage 1/{len(problem.stages)} "
                        f"(1/{problem.stages[0].scale} resolution)")
    forks = [search.forked() for _ in starts]

    def first_stage(i: int) -> tuple[Pose, float, int]:
        vec, loss = forks[i].nelder_mead(0, starts[i].vector(), i)
        return Pose.from_vector(vec), loss, forks[i].counter.evaluations

    coarse = side_by_side(first_stage, range(n))
    counter.join([f.counter for f in forks])
    basin, heads = _basins([c[0] for c in coarse], [c[1] for c in coarse],
                           vp.merge_translation_m, vp.merge_rotation_deg)
    limit = coarse[heads[0]][1] * (1.0 + vp.refine_margin) + vp.loss_margin_abs
    chosen = [i for i in heads if coarse[i][1] <= limit][: vp.refine_max]
    # refinement minimises the problem's own loss (a coverage term would pull the pose towards
    # more coverage); the coverage term only ranks the refined basins against each other
    weight, search.coverage_weight = search.coverage_weight, 0.0
    refined, unfinished = _refined(problem, search,
                                   [(i, coarse[i][0], coarse[i][1]) for i in chosen])
    for i, (pose, loss, evals) in unfinished.items():  # reported as not refined (no rival)
        coarse[i] = (pose, loss, coarse[i][2] + evals)
    counter.report()
    rank = {i: refined[i][1] + (weight * (1.0 - problem.evaluate(refined[i][0]).coverage)
                                if weight > 0 and len(refined) > 1 else 0.0) for i in refined}
    win = min(refined, key=lambda i: rank[i])
    best_pose, best_loss = refined[win][0], refined[win][1]
    if params.loss.outlier_width_px > 0:
        best_pose, best_loss = _without_label_outliers(problem, search, best_pose, best_loss, win)
    final = problem.evaluate(best_pose)
    if problem.degenerate(final):
        raise CalibrationFailed(
            f"at the best pose found the map covers "
            f"{final.coverage * 100:.1f} % of the labelled image (loss {final.loss:.4g}); "
            "the initial pose is probably far from the truth, or the map is not of this camera's "
            "view", counter.evaluations, time.perf_counter() - t0)
    # renumber the basins so the result's is 0, the others in order of coarse loss
    order = {b: k for k, b in enumerate(
        [basin[win]] + [b for b in range(len(heads)) if b != basin[win]])}
    runs = []
    for i, start in enumerate(starts):
        pose, loss, evals = refined[i] if i in refined else coarse[i]
        extra = coarse[i][2] if i in refined else 0
        runs.append(RunResult(start, pose, float(loss), int(evals + extra), float(coarse[i][1]),
                              i in refined, order[basin[i]]))
    counter.begin_stage("quality report")
    evidence = _evidence(problem, search, best_pose)
    # the report measures the agreeing starts' spread and the coverage: the result refers to it
    quality = assess(problem, best_pose, runs, on_probe=counter.check, start=initial,
                     evidence=evidence, at_bounds=search.at_face(best_pose.vector(),
                                                                  best_loss))
    return CalibrationResult(
        pose=best_pose, loss=float(best_loss), evaluations=counter.evaluations + quality.evaluations,
        seconds=time.perf_counter() - t0, history=counter.history, runs=runs,
        accepted=sum(r.basin == 0 for r in runs), quality=quality,
    )


def calibrate(map_cloud: LabelledCloud, target: np.ndarray, camera: CameraModel, initial: Pose,
              params: CalibrationParams | None = None, mapping: LabelMapping | None = None,
              seed: int | None = None, progress: Callable[[Progress], None] | None = None,
              should_stop: Callable[[], bool] | None = None,
              probabilities: np.ndarray | None = None) -> CalibrationResult:
    """Find the camera pose in the map frame (see the module docstring). The map is cropped
    around the initial position; preparing it is counted in the result's seconds.
    ``probabilities``: the segmenter's softmax beside the labels (Problem)."""
    t0 = time.perf_counter()
    problem = Problem(map_cloud, target, camera, initial.translation, params, mapping,
                      probabilities=probabilities)
    result = solve(problem, initial, seed, progress, should_stop)
    result.seconds = time.perf_counter() - t0
    return result
