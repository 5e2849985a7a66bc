"""The uncertainty from independent evidence (engine/evidence.py) and the verdict built on it
(engine/quality.py): which parts a problem splits into, the spread formulas, and how the starts
that ended as low join the +- or contradict the result."""

from __future__ import annotations

import numpy as np
import pytest

from semcal_ros.engine.evidence import (STRIPS, Evidence, axis_offsets, evidence_uncertainty,
                                        independent_parts, strips)
from semcal_ros.engine.frames import FrameSet
from semcal_ros.engine.labels import INVALID
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.quality import assess
from semcal_ros.engine.results import RunResult
from semcal_tools.synthetic import GROUND_TRUTH, camera, target_image


@pytest.fixture(scope="module")
def problem(world, target):
    return Problem(world, target, camera(), GROUND_TRUTH.translation)


def moved(dx: float = 0.0, dy: float = 0.0, dyaw: float = 0.0) -> Pose:
    return Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [dx, dy, 0.0],
                                  GROUND_TRUTH.body_rpy_deg() + [0.0, 0.0, dyaw])


def test_strips_cut_every_column_once():
    parts = strips(1241)
    assert len(parts) == STRIPS
    assert np.array_equal(np.sum(parts, axis=0), np.ones(1241))


def test_a_single_frame_leaves_each_strip_out_in_turn(problem):
    method, groups = independent_parts(problem)
    assert "4 image strips" in method and len(groups) == 1 and len(groups[0]) == STRIPS
    w = problem.target.shape[1]
    for part, strip in zip(groups[0], strips(w)):
        assert np.all(part.target[:, strip] == INVALID)
        assert np.array_equal(part.target[:, ~strip], problem.target[:, ~strip])


def test_frames_are_left_out_in_turn_and_two_stand_alone(problem):
    method, groups = independent_parts(FrameSet([problem] * 4))
    assert method == "leave-one-out of 4 frames"
    assert [len(p.frames) for p in groups[0]] == [3, 3, 3, 3]
    method, groups = independent_parts(FrameSet([problem] * 2))
    assert method == "each of 2 frames alone" and groups[0] == [problem, problem]


def test_the_jackknife_and_the_halves_formulas(problem):
    """Four parts that end 0, 0, 0 and 4 cm along x: the jackknife's sigma is
    sqrt(3/4 x sum (x_i - mean)^2) = 3 cm; two frames 4 cm apart give |A - B| / 2 = 2 cm."""
    ends = iter([0.0, 0.0, 0.0, 0.04])
    shared_flags = []

    def refine(parts, start, shared):
        shared_flags.append(shared)
        return [moved(dx=next(ends)).vector() for _ in parts]

    ev = evidence_uncertainty(problem, GROUND_TRUTH, refine)
    assert ev.parts == 4 and ev.sigma[0] == pytest.approx(0.03, abs=1e-9)
    assert ev.moves[0] == pytest.approx(0.04, abs=1e-9) and ev.sigma[1] == pytest.approx(0.0)
    ends = iter([0.0, 0.04])
    ev = evidence_uncertainty(FrameSet([problem] * 2), GROUND_TRUTH, refine)
    assert ev.sigma[0] == pytest.approx(0.02, abs=1e-9)
    # a single frame's strips are copies of their own; a frame set's parts are its own frames
    assert shared_flags == [False, True]


def test_axis_offsets_wrap_the_angles():
    a = Pose.from_body_rpy_deg([0, 0, 0], [0, 0, 179.0])
    b = Pose.from_body_rpy_deg([0, 0, 0], [0, 0, -179.0])
    assert axis_offsets(a, b)[5] == pytest.approx(-2.0, abs=1e-9)


def _evidence(cm: float, deg: float) -> Evidence:
    s = np.array([cm / 100] * 3 + [0.0, deg, deg])
    return Evidence(s, s, "test", 4)


def test_good_needs_independent_evidence_within_the_tolerance(problem):
    loss = problem.loss(GROUND_TRUTH)
    runs = [RunResult(GROUND_TRUTH, GROUND_TRUTH, loss, 10, loss, True, 0)]
    q = assess(problem, GROUND_TRUTH, runs, evidence=_evidence(2.0, 0.03))
    assert q.verdict == "good", q.summary()
    assert q.uncertainty_translation_m == pytest.approx((0.06, 0.06, 0.06))  # 3 sigma
    assert q.uncertainty_method == "test" and q.evaluations == 1  # no probes
    q = assess(problem, GROUND_TRUTH, runs, evidence=_evidence(5.0, 0.03))
    assert q.verdict == "inconclusive" and "more frames" in q.reason, q.summary()


def test_a_start_as_low_joins_the_uncertainty_or_contradicts_the_result(problem):
    loss, floor = problem.loss(GROUND_TRUTH), problem.floor(GROUND_TRUTH)
    as_low = loss + 0.01 * (loss - floor)
    ev = _evidence(10.0, 0.1)  # +- 30 cm per axis: 3 x its norm reaches about 1.6 m
    near = moved(dx=0.4)
    runs = [RunResult(GROUND_TRUTH, GROUND_TRUTH, loss, 10, loss, True, 0),
            RunResult(near, near, as_low, 10, loss, True, 1)]
    q = assess(problem, GROUND_TRUTH, runs, evidence=ev)
    assert q.verdict == "inconclusive", q.summary()  # within reach: the +- widens to it
    assert q.uncertainty_translation_m[0] == pytest.approx(0.4, abs=1e-6)
    far = moved(dx=2.2)
    runs[1] = RunResult(far, far, as_low, 10, loss, True, 1)
    q = assess(problem, GROUND_TRUTH, runs, evidence=ev)
    assert q.verdict == "failed" and "runs disagree" in q.reason, q.summary()
    # a failed result says no more than its prior: the +- is the search's bounds
    assert q.uncertainty_translation_m == problem.params.search.bound_xyz


def test_a_result_at_the_bounds_of_its_search_fails(problem):
    from semcal_ros.engine.search import EvaluationCounter, Search

    search = Search(problem, EvaluationCounter(None, None))
    search.confine(GROUND_TRUTH)
    bound = problem.params.search.bound_xyz[0]
    # the truth at the face of a box centred 2.5 m away: near the face, but not held back there
    search.confine(moved(dx=-bound))
    assert not search.at_face(GROUND_TRUTH.vector(), problem.loss(GROUND_TRUTH))
    # a box whose face lies 2.5 m short of the truth: a result held there, the loss falls beyond
    search.confine(moved(dx=-2 * bound))
    edge = moved(dx=-bound)
    assert search.at_face(edge.vector(), problem.loss(edge))
    q = assess(problem, GROUND_TRUTH, (), evidence=_evidence(1.0, 0.01), at_bounds=True)
    assert q.verdict == "failed" and "bounds" in q.reason, q.summary()


def test_the_calibration_reports_its_evidence(world):
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.search import calibrate
    from semcal_tools.synthetic import PERTURBED_START

    target = target_image(camera(), world=world)
    res = calibrate(world, target, camera(), PERTURBED_START, CalibrationParams(), seed=0)
    q = res.quality
    assert q.uncertainty_method == f"leave-one-out of {STRIPS} image strips"
    assert len(q.evidence_sigma) == 6 and max(q.evidence_sigma[:3]) < 0.05, q.evidence_sigma
    assert q.verdict == "good", q.summary()
