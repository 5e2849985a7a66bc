"""The engine's pieces: parameters, the problem (one prepared map, a public loss), the search."""

from pathlib import Path

import numpy as np
import pytest

from semcal_ros.engine.params import (
    CalibrationParams, LabelParams, ScheduleParams, SearchParams, Stage, VerificationParams,
)
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.engine.problem import Problem
from semcal_tools.synthetic import GROUND_TRUTH, PERTURBED_START, camera

INITIAL = PERTURBED_START


@pytest.fixture(scope="module")
def problem(world, target):
    return Problem(world, target, camera(), GROUND_TRUTH.translation)


# --- parameters --------------------------------------------------------------------------------
def test_schedule_is_a_tuple_of_stage_records():
    stages = ScheduleParams().stages()
    assert [s.scale for s in stages] == [4, 2, 1]
    assert stages[-1] == Stage(1, 0.03, 1e-6, ScheduleParams().max_evaluations[-1], 1)
    with pytest.raises(ValueError, match="one entry per stage"):
        ScheduleParams(scales=(4, 1), simplex=(1.0,))
    with pytest.raises(ValueError, match="last stage must be at full resolution"):
        ScheduleParams(scales=(4, 2), simplex=(1, 1), fatol=(1, 1), max_evaluations=(1, 1),
                       restarts=(0, 0))
    with pytest.raises(ValueError, match="max_evaluations"):
        ScheduleParams(max_evaluations=(300, -1, 80))


@pytest.mark.parametrize("kwargs,message", [
    ({"bound_xyz": (1e9, 2.5, 2.5)}, "at most 50 m"),
    ({"bound_yaw_deg": 1e9}, "beyond 180 deg"),
    ({"bound_pitch_deg": float("nan")}, "search.bound_pitch_deg must be a finite number"),
    ({"bound_xyz": (2.5, -1.0, 2.5)}, "positive"),
])
def test_search_bounds_are_refused_with_the_limit_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SearchParams(**kwargs)


def test_parameter_file_engine_group(tmp_path: Path):
    good = tmp_path / "good.yaml"
    good.write_text("calibrator:\n  ros__parameters:\n    seed: 3\n    engine:\n"
                    "      labels: {merge: ['sidewalk:road']}\n      loss: {crop_top: 0.5}\n")
    p = CalibrationParams.from_file(good)
    assert p.labels.as_dict() == {"sidewalk": "road"} and p.loss.crop_top == 0.5
    stray = tmp_path / "stray.yaml"
    stray.write_text("calibrator:\n  ros__parameters:\n    loss: {crop_top: 0.5}\n")
    with pytest.raises(ValueError, match="loss must stand under 'engine:'"):
        CalibrationParams.from_file(stray)
    typo = tmp_path / "typo.yaml"
    typo.write_text("calibrator:\n  ros__parameters:\n    engine: {loss: {kindd: l2}}\n")
    with pytest.raises(ValueError, match="loss.kindd"):
        CalibrationParams.from_file(typo)
    with pytest.raises(ValueError, match="'from:to'"):
        LabelParams(merge=("road",))


def test_shipped_config_equals_the_defaults():
    path = Path(__file__).parents[1] / "config" / "calibrator.yaml"
    assert CalibrationParams.from_file(path) == CalibrationParams()


# --- the problem -------------------------------------------------------------------------------
def test_problem_loss_is_lowest_at_the_truth_at_every_stage(problem):
    for stage in range(len(problem.stages)):
        at_truth = problem.loss(GROUND_TRUTH, stage)
        assert at_truth < problem.loss(INITIAL, stage)
        assert problem.render(GROUND_TRUTH, stage).shape == \
            (camera().height // problem.stages[stage].scale,
             camera().width // problem.stages[stage].scale)
    ev = problem.evaluate(GROUND_TRUTH)
    assert ev.coverage > 0.5 and not problem.degenerate(ev)
    assert problem.degenerate(problem.evaluate(Pose.from_body_rpy_deg([0, 0, 6], [0, -80, 0])))


def test_problem_prepares_the_map_once_around_an_explicit_centre(world, target):
    far = GROUND_TRUTH.translation + [30.0, 0.0, 0.0]
    p = Problem(world, target, camera(), far)
    np.testing.assert_allclose(p.pmap.origin, far)
    with pytest.raises(ValueError, match="m from the nearest map point"):
        Problem(world, target, camera(), GROUND_TRUTH.translation + [1e5, 0, 0])
    with pytest.raises(ValueError, match="label image is 10x10"):
        Problem(world, np.zeros((10, 10), np.uint8), camera(), GROUND_TRUTH.translation)


def test_label_merge_from_parameters_reaches_both_domains(world, target):
    from semcal_ros.engine.labels import CITYSCAPES_ID

    p = Problem(world, target, camera(), GROUND_TRUTH.translation,
                CalibrationParams(labels=LabelParams(merge=("sidewalk:road",))))
    assert not np.any(p.target == CITYSCAPES_ID["sidewalk"])
    assert not np.any(p.pmap.label == CITYSCAPES_ID["sidewalk"])


# --- the search --------------------------------------------------------------------------------
def test_full_procedure_refines_few_basins_and_recovers_the_pose(problem):
    from semcal_ros.engine.evidence import STRIPS
    from semcal_ros.engine.search import solve

    params = problem.params
    res = solve(problem, INITIAL, seed=1)
    # the default loss (boundary band 4 px) is quadratic near an exact optimum, where the paper's
    # is V-shaped: the search stops ~0.01 deg less sharply on this exact target (0.066 vs < 0.06)
    assert translation_error(res.pose, GROUND_TRUTH) < 0.03
    assert rotation_error_deg(res.pose, GROUND_TRUTH) < 0.08
    assert len(res.runs) == 1 + params.verification.starts
    refined = [r for r in res.runs if r.refined]
    assert 1 <= len(refined) <= params.verification.refine_max
    assert res.accepted == sum(r.basin == 0 for r in res.runs) >= 1
    # every render counts: the search's (history) and the quality report's
    assert res.evaluations == len(res.history) + res.quality.evaluations
    assert res.quality.verdict == "good", res.quality.summary()
    # full resolution is spent only on the refined runs, plus one score of each other basin
    # chosen for refinement where its half-resolution stage ended (verification.refine_final)
    # (and the uncertainty's refinements on independent parts of the image, engine/evidence.py)
    full = sum(1 for run, stage, _ in res.history if stage == len(problem.stages) - 1)
    assert full <= len(refined) * params.schedule.max_evaluations[-1] * \
        (1 + params.schedule.restarts[-1]) + len(refined) + params.verification.refine_max + \
        STRIPS * params.quality.evidence_evaluations


def test_basins_merge_starts_that_end_together():
    from semcal_ros.engine.search import _basins

    a = Pose.from_body_rpy_deg([0, 0, 5], [0, 10, 0])
    b = Pose.from_body_rpy_deg([0.1, 0, 5], [0, 10.1, 0])  # 10 cm, 0.1 deg from a
    c = Pose.from_body_rpy_deg([2.0, 0, 5], [0, 10, 0])
    basin, heads = _basins([b, c, a], [0.2, 0.15, 0.1], 0.3, 0.3)
    assert basin == [0, 1, 0] and heads == [2, 1]


def test_degenerate_result_is_an_error_not_a_result(world, target):
    from semcal_ros.engine.loss import LossParams
    from semcal_ros.engine.search import calibrate

    # every loss counts as the degenerate value: whatever the search finds is no result
    params = CalibrationParams(loss=LossParams(degenerate_loss=1e-12),
                               verification=VerificationParams(starts=0),
                               schedule=ScheduleParams(scales=(4, 1), simplex=(1.0, 0.03),
                                                       fatol=(1e-4, 1e-6),
                                                       max_evaluations=(10, 3),
                                                       restarts=(0, 0)))
    with pytest.raises(ValueError, match="calibration failed: at the best pose found"):
        calibrate(world, target, camera(), INITIAL, params)


def test_yaw_grid_finds_an_unknown_yaw(world, target):
    from semcal_ros.engine.search import EvaluationCounter, Search, _yaw_candidates

    lost = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [0.5, -0.5, 0.3],
                                  GROUND_TRUTH.body_rpy_deg() + [0.0, 2.0, 97.0])
    params = CalibrationParams(search=SearchParams(yaw_search=True, yaw_search_keep=3))
    search = Search(Problem(world, target, camera(), lost.translation, params),
                    EvaluationCounter(None, None))
    candidates = _yaw_candidates(search, lost)
    yaw_errors = [abs((c.body_rpy_deg()[2] - GROUND_TRUTH.body_rpy_deg()[2] + 180) % 360 - 180)
                  for c in candidates]
    assert min(yaw_errors) <= 5.0  # a grid cell within the +-5 deg search bound of the truth
    # after the short descent the right heading ranks first
    assert yaw_errors[0] <= 5.0, yaw_errors


def test_the_yaw_search_stays_within_the_prior_and_scores_coverage(problem):
    """Confined: a pose beyond 1.5 x the bounds of the initial guess (x, y, z, pitch) costs the
    degenerate loss without a render, one inside costs the loss plus the coverage term; a
    descent from the edge of the box ends inside it."""
    from semcal_ros.engine.search import EvaluationCounter, Search

    search = Search(problem, EvaluationCounter(None, None))
    search.confine(INITIAL, 1.5)
    search.coverage_weight = 0.2
    v = INITIAL.vector()
    out = v.copy()
    out[0] += 2.5 * 1.5 + 0.01
    assert search.score(Pose.from_vector(out), 0) == problem.params.loss.degenerate_loss
    tilted = v.copy()
    tilted[4] += np.radians(5.0 * 1.5 + 0.1)
    assert search.outside(tilted) and not search.outside(v)
    e = problem.evaluate(GROUND_TRUTH, 0)
    assert search.score(GROUND_TRUTH, 0) == pytest.approx(e.loss + 0.2 * (1 - e.coverage))
    edge = v.copy()
    edge[1] += 2.5 * 1.4
    end, _ = search.nelder_mead(0, edge, 0, 60)
    assert not search.outside(end)
    search.confine(INITIAL, 0.0)  # 0: unconfined, the paper's search
    assert not search.outside(out)


def test_free_roll_adds_a_parameter(problem, world, target):
    from semcal_ros.engine.search import EvaluationCounter, Search

    fixed = Search(problem, EvaluationCounter(None, None))
    free = Search(Problem(world, target, camera(), INITIAL.translation,
                          CalibrationParams(search=SearchParams(free_roll=True))),
                  EvaluationCounter(None, None))
    assert list(fixed.free) == [0, 1, 2, 4, 5]
    assert list(free.free) == [0, 1, 2, 3, 4, 5]
    moved = free.pose_at(INITIAL.vector(), np.array([0, 0, 0, 1.0, 0, 0]))
    assert moved.body_rpy_deg()[0] == pytest.approx(INITIAL.body_rpy_deg()[0] + 2.0)


def test_a_masked_problem_shares_the_map_and_leaves_the_pixels_out(problem, world, target):
    from semcal_ros.engine.labels import INVALID

    off = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [0.3, 0, 0], GROUND_TRUTH.body_rpy_deg())
    ignore = np.zeros(target.shape, bool)
    ignore[: target.shape[0] // 2] = True
    masked = problem.masked(ignore)
    assert masked.pmap is problem.pmap and masked.camera is problem.camera
    by_hand = Problem(world, np.where(ignore, INVALID, target).astype(np.uint8), camera(),
                      GROUND_TRUTH.translation, prepared=problem.pmap)
    for stage in range(len(problem.stages)):
        assert masked.loss(off, stage) == pytest.approx(by_hand.loss(off, stage))
    assert masked.loss(off) != pytest.approx(problem.loss(off))


def test_the_label_error_refinement_keeps_an_exact_solution(world, target):
    from dataclasses import replace

    from semcal_ros.engine.loss import LossParams
    from semcal_ros.engine.search import solve

    params = replace(CalibrationParams(), loss=LossParams(outlier_width_px=9.0),
                     verification=replace(CalibrationParams().verification, starts=1))
    p = Problem(world, target, camera(), GROUND_TRUTH.translation, params)
    near = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [0.5, -0.4, 0.3],
                                  GROUND_TRUTH.body_rpy_deg() + [0.0, 1.0, -1.0])
    res = solve(p, near, seed=0)
    assert translation_error(res.pose, GROUND_TRUTH) < 0.03
    assert res.loss == pytest.approx(p.loss(res.pose))


def test_a_stage_ends_when_its_loss_stops_improving(problem):
    """schedule.stall_evaluations (issue 19): a Nelder-Mead stage whose best loss has not dropped
    by more than the stage's fatol for that many evaluations ends there. The search is
    deterministic, so the stopped stage is the unstopped one cut short: same evaluations, in the
    same order, up to the stop."""
    import copy
    from dataclasses import replace

    from semcal_ros.engine.search import EvaluationCounter, Search

    histories = {}
    for stall in (0, 12):
        p = copy.copy(problem)
        p.params = replace(problem.params,
                           schedule=replace(problem.params.schedule, stall_evaluations=stall))
        counter = EvaluationCounter(None, None)
        Search(p, counter).coarse(INITIAL, 0, "test")
        histories[stall] = [loss for _, _, loss in counter.history]
    full, cut = histories[0], histories[12]
    assert len(cut) < len(full)
    assert cut == full[:len(cut)]
    fatol = problem.stages[0].fatol
    mark, since = np.inf, 0
    for value in cut:
        mark, since = (value, 0) if value < mark - fatol else (mark, since + 1)
    assert since == 12  # it stopped exactly when the rule says, not before


def test_only_the_best_basin_runs_the_last_stage_unless_another_comes_near(world, target):
    """verification.refine_final 1: of the basins chosen for refinement, the best after the
    stage before the last runs the full-resolution stage; another ends at half resolution,
    scored once at full resolution, unless it comes near the best there. With 0 every chosen
    basin runs every stage; the best pose is the same."""
    from dataclasses import replace

    from semcal_ros.engine.search import EvaluationCounter, Search, _refined

    base = CalibrationParams()
    far = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [2.0, -1.5, 0.5],
                                 GROUND_TRUTH.body_rpy_deg() + [0, 4, -4])
    found = {}
    for final in (1, 0):
        params = replace(base, verification=replace(base.verification, refine_final=final))
        problem = Problem(world, target, camera(), GROUND_TRUTH.translation, params)
        last = len(problem.stages) - 1
        basins = [(k, pose, problem.loss(pose, 0)) for k, pose in enumerate((INITIAL, far))]
        counter = EvaluationCounter(None, None)
        done, rest = _refined(problem, Search(problem, counter), basins)
        assert sorted([*done, *rest]) == [0, 1]
        assert (len(done), len(rest)) == ((2, 0) if final == 0 else (1, 1))
        for pose, loss, _ in rest.values():  # scored once at full resolution where it stopped
            assert loss == pytest.approx(problem.loss(pose, last))
            assert loss > min(d[1] for d in done.values())
        found[final] = min(done.values(), key=lambda d: d[1])
        assert counter.evaluations == len(counter.history)
    assert translation_error(found[1][0], GROUND_TRUTH) < 0.05
    assert translation_error(found[1][0], found[0][0]) < 0.02
    assert rotation_error_deg(found[1][0], found[0][0]) < 0.05
