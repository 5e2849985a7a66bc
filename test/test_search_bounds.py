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


# --- the doors: the CLI, the action's goal, the drift check ------------------------------------
def test_the_cli_keeps_the_result_within_its_bounds(tmp_path, world, target):
    """`semcal calibrate` with bounds of 0.5 m / 2 deg in its parameter file, from a start the
    truth is 1.2-1.8 m from: the written pose stays within 0.5 m / 2 deg of the start."""
    import yaml

    from semcal_ros.cli import main
    from semcal_ros.io import files, ply

    ply.write_ply(tmp_path / "map.ply", world)
    files.write_label_image(tmp_path / "labels.png", target)
    files.write_camera_info(tmp_path / "camera_info.yaml", camera())
    files.write_pose(tmp_path / "initial.yaml", PERTURBED_START)
    engine = {"search": {"bound_xyz": [0.5, 0.5, 0.5], "bound_pitch_deg": 2.0,
                         "bound_yaw_deg": 2.0}, "verification": {"starts": 1}}
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(
        {"calibrator": {"ros__parameters": {"engine": engine}}}))
    code = main(["calibrate", "--map", str(tmp_path / "map.ply"),
                 "--labels", str(tmp_path / "labels.png"),
                 "--camera-info", str(tmp_path / "camera_info.yaml"),
                 "--initial", str(tmp_path / "initial.yaml"), "--config", str(tmp_path / "p.yaml"),
                 "--output", str(tmp_path / "out.yaml"), "--quiet"])
    assert code == 0
    d = _offsets(files.read_pose(tmp_path / "out.yaml"), PERTURBED_START)
    assert np.all(d[:3] <= 0.5 + 1e-6) and np.all(d[4:] <= np.radians(2.0) + 1e-9), d


def test_the_action_goal_bounds_reach_the_search(world, target):
    """The action's goal carries bounds (0 = the node's): they become the engine's, and the
    search run on them stays inside (the node calls ``solve`` with ``goal_params``)."""
    from types import SimpleNamespace

    from semcal_ros.ros.calibrate_goal import goal_params

    def vec(x: float, y: float, z: float) -> SimpleNamespace:  # a geometry_msgs Vector3
        return SimpleNamespace(x=x, y=y, z=z)

    goal = SimpleNamespace(bound_translation_m=vec(0.4, 0.4, 0.0), bound_rpy_deg=vec(0.0, 1.5, 1.5),
                           roll="", yaw_search="", verification_starts=1, loss="")
    params = goal_params(goal, CalibrationParams())
    assert params.search.bound_xyz == (0.4, 0.4, 2.5)
    problem = Problem(world, target, camera(), GROUND_TRUTH.translation, params)
    res = solve(problem, PERTURBED_START, seed=0)
    d = _offsets(res.pose, PERTURBED_START)
    limit = np.array([0.4, 0.4, 2.5, 1e-9, np.radians(1.5), np.radians(1.5)])
    assert np.all(d <= limit * (1 + 1e-6)), d


def test_the_drift_check_stays_within_its_bounds(world, target):
    """A camera knocked 0.6 m, beyond the check's 0.25 m bounds: the check's estimate stops at
    the bounds, it does not wander after the loss."""
    from semcal_ros.engine.drift import DriftParams, check_drift, check_params

    dp = DriftParams()
    params = check_params(CalibrationParams(), dp)
    problem = Problem(world, target, camera(), GROUND_TRUTH.translation, params)
    v = GROUND_TRUTH.vector()
    v[0] += 0.6
    calibrated = Pose.from_vector(v)  # the held calibration; the camera now sees the truth
    report = check_drift(problem, calibrated, dp)
    assert report.estimated is not None, report.message
    d = _offsets(report.estimated, calibrated)
    assert np.all(d[:3] <= dp.bound_m + 1e-6), d
    assert np.all(d[3:] <= np.radians(dp.bound_deg) + 1e-9), d
    assert d[0] > 0.5 * dp.bound_m, d  # it followed the knock as far as the bounds allow
