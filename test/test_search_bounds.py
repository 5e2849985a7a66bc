"""The search stays inside the prior it is given: no result farther from its start than the
bounds on any axis, whatever the loss prefers beyond them (the engine's door; the CLI's and the
action's go through ``solve``)."""

from dataclasses import replace

import numpy as np
import pytest

from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.search import EvaluationCounter, Search, box_offset, solve
from semcal_tools.synthetic import GROUND_TRUTH, PERTURBED_START, camera


def _offsets(result: Pose, start: Pose) -> np.ndarray:
    return box_offset(result.vector(), start.vector())


@pytest.mark.parametrize("loss", ["l2", "likelihood"])
def test_a_result_never_leaves_the_bounds_of_its_start(world, target, loss):
    """The truth lies 1.8 / 1.5 / 1.2 m and 3.5 / 4 deg from the start; with bounds of 0.6 m and
    2 deg the loss's minimum is outside the prior: the result stops at the bounds, not beyond."""
    base = CalibrationParams()
    params = replace(base, loss=replace(base.loss, kind=loss),
                     search=replace(base.search, bound_xyz=(0.6, 0.6, 0.6), bound_pitch_deg=2.0,
                                    bound_yaw_deg=2.0),
                     verification=replace(base.verification, starts=2))
    problem = Problem(world, target, camera(), GROUND_TRUTH.translation, params)
    res = solve(problem, PERTURBED_START, seed=3)
    d = _offsets(res.pose, PERTURBED_START)
    limit = np.array([0.6, 0.6, 0.6, 1e-9, np.radians(2.0), np.radians(2.0)])
    assert np.all(d <= limit * (1 + 1e-6)), d
    # the search went as far as the prior lets it towards the truth, on some axis
    assert np.max(d[:3] / 0.6) > 0.5
    for run in res.runs:  # every start and every run's end, too
        assert np.all(_offsets(run.pose, PERTURBED_START) <= limit * (1 + 1e-6))


def test_the_box_wraps_angles_and_frees_yaw_only_when_asked(world, target):
    problem = Problem(world, target, camera(), GROUND_TRUTH.translation)
    search = Search(problem, EvaluationCounter(None, None))
    search.confine(PERTURBED_START)
    v = PERTURBED_START.vector()
    turned = v.copy()
    turned[5] += np.radians(5.5)
    assert search.outside(turned)
    search.confine(PERTURBED_START, yaw=False)
    assert not search.outside(turned)
    wrapped = v.copy()
    wrapped[5] += 2 * np.pi  # the same heading
    search.confine(PERTURBED_START)
    assert not search.outside(wrapped)
