"""Work side by side (engine/workers.py): the order kept, renders on the worker's own thread,
nested calls in line, and a calibration that ends where it ends one step after another."""

import threading
from dataclasses import replace

import numba
import numpy as np

from semcal_ros.engine import workers
from semcal_ros.engine.frames import FrameSet
from semcal_ros.engine.params import (
    CalibrationParams, QualityParams, ScheduleParams, VerificationParams,
)
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.search import solve
from semcal_tools.synthetic import PERTURBED_START, camera

#: Short searches: what is compared is the two ways of running them, not how far they get, and
#: equal paths are equal at any length (the default schedule made these two tests 49 s of the
#: suite). Two verification starts and the evidence's parts still run side by side.
SHORT = CalibrationParams(
    schedule=ScheduleParams(max_evaluations=(60, 30, 20)),
    verification=VerificationParams(starts=2),
    quality=QualityParams(evidence_evaluations=15))


def test_side_by_side_keeps_the_order_and_runs_nested_calls_in_line():
    here = threading.get_ident()

    def inner(x):
        return x, workers.render_threads(), threading.get_ident()

    def outer(x):
        return workers.render_threads(), workers.side_by_side(inner, [x, x + 1]), \
            threading.get_ident()

    out = workers.side_by_side(outer, range(6))
    assert [[i[0] for i in o[1]] for o in out] == [[x, x + 1] for x in range(6)]
    assert workers.render_threads() is None and not workers.on_worker()
    if numba.get_num_threads() > 1:
        assert all(o[0] == 1 and o[2] != here for o in out)  # on a worker, drawing on it
        # a worker's own side_by_side runs in line on that worker: the pool never waits on itself
        assert all(i[1] == 1 and i[2] == o[2] for o in out for i in o[1])


def test_a_calibration_side_by_side_ends_where_one_step_after_another_does(world, target):
    """The starts' coarse stages and the evidence's parts run side by side on the workers; with
    one thread (no workers) the same searches run in turn on the renderer's pool. Same pose,
    evaluations, history (joined in order) and uncertainty."""
    side = solve(Problem(world, target, camera(), PERTURBED_START.translation, SHORT),
                 PERTURBED_START, seed=0)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        in_turn = solve(Problem(world, target, camera(), PERTURBED_START.translation, SHORT),
                        PERTURBED_START, seed=0)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(side.pose.vector(), in_turn.pose.vector())
    assert side.evaluations == in_turn.evaluations and side.history == in_turn.history
    assert side.quality.evidence_sigma == in_turn.quality.evidence_sigma
    assert side.quality.verdict == in_turn.quality.verdict


def test_a_frame_set_side_by_side_ends_where_one_step_after_another_does(world, target):
    """Two frames: the evidence's parts (each frame alone) are the set's own frames, share one
    E step taken for both, and run side by side; the same answer as in turn."""
    params = replace(SHORT, verification=VerificationParams(starts=1))

    def rig() -> FrameSet:
        return FrameSet([Problem(world, target, camera(), PERTURBED_START.translation, params)
                         for _ in range(2)])

    side = solve(rig(), PERTURBED_START, seed=0)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        in_turn = solve(rig(), PERTURBED_START, seed=0)
    finally:
        numba.set_num_threads(threads)
    assert side.quality.uncertainty_method == "each of 2 frames alone"
    assert np.array_equal(side.pose.vector(), in_turn.pose.vector())
    assert side.history == in_turn.history
    assert side.quality.evidence_sigma == in_turn.quality.evidence_sigma
