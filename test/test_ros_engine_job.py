"""The engine-job machinery (semcal_ros.ros.engine_job) without DDS: one engine thread, jobs in
arrival order, one goal per key, a cancel answered at once and a queued job that never starts.
The node and goal handles are stand-ins with the few attributes the runner uses."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

pytest.importorskip("rclpy")

from semcal_ros.ros.engine_job import EngineJob, GoalRunner, JobCancelled  # noqa: E402


class _Node:
    def __init__(self) -> None:
        self.context = SimpleNamespace(ok=lambda: True)

    def create_timer(self, period, callback, callback_group=None):
        return None

    def get_logger(self):
        return SimpleNamespace(debug=lambda *_: None)


def _wait_for(predicate, what: str, timeout: float = 30.0) -> None:
    """Poll ``predicate`` until true; the deadline is generous (a loaded machine), never a pace."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def _handle() -> SimpleNamespace:
    return SimpleNamespace(is_cancel_requested=False, publish_feedback=lambda _: None)


def test_goals_queue_one_per_key_and_a_cancelled_queued_job_never_starts():
    runner = GoalRunner(_Node(), 0.5, lambda state: state.stage)
    order: list[str] = []
    gate = threading.Event()

    def work(name: str):
        def run(job: EngineJob) -> str:
            order.append(name)
            if name == "north":
                gate.wait(60)  # held until the test has checked the queue
            return name
        return run

    north = runner.claim("north", "aaaa", _handle())
    assert runner.claim("north", "bbbb", _handle()).startswith(
        "busy: goal aaaa for camera 'north' has been running for ")
    south = runner.claim("south", "cccc", _handle())
    east = runner.claim("east", "dddd", _handle())
    jobs = {k: EngineJob(work(k)) for k in ("north", "south", "east")}
    outcomes: dict[str, str] = {}
    threads = [threading.Thread(target=lambda s=s, k=k: outcomes.__setitem__(
        k, runner.run(s, jobs[k]))) for k, s in (("north", north), ("south", south),
                                                ("east", east))]
    for t, state in zip(threads, (north, south, east)):
        t.start()  # arrival order: the next goal arrives once this one is submitted
        _wait_for(lambda: state.submitted, f"goal {state.goal_id} to be submitted")
    _wait_for(lambda: north.running, "north to start")
    assert north.running and south.stage == "queued" and east.stage == "queued"
    text = runner.claim("south", "eeee", _handle())
    assert text.startswith("busy: goal cccc for camera 'south' is queued (") and \
        text.endswith("(one calibration per camera at a time)")
    east.handle.is_cancel_requested = True  # cancelled while queued: answered at once
    threads[2].join(30)
    assert outcomes["east"] == "cancelled"
    runner.release(east, jobs["east"])
    assert runner.state("east") is not None  # its job has not ended yet: the key stays busy
    gate.set()
    for t in threads[:2]:
        t.join(30)
    assert outcomes == {"north": "done", "south": "done", "east": "cancelled"}
    assert jobs["east"].done.wait(30)  # the worker took it after south's, and skipped it
    assert order == ["north", "south"]  # east never ran
    assert jobs["north"].result == "north" and isinstance(jobs["east"].error, JobCancelled)
    for state, job in ((north, jobs["north"]), (south, jobs["south"])):
        runner.release(state, job)
    _wait_for(lambda: not runner.states(), "every key to be freed")  # east's: when its job ended
    runner.close()


def test_a_goal_claimed_behind_a_submitted_one_says_queued_from_its_first_feedback():
    """The feedback timer may fire between claim and run: the stage is right from the claim."""
    runner = GoalRunner(_Node(), 0.5, lambda state: state.stage)
    gate = threading.Event()
    north = runner.claim("north", "aaaa", _handle())
    assert north.stage == "preparing"  # nothing ahead of it
    job = EngineJob(lambda j: gate.wait(60))
    thread = threading.Thread(target=runner.run, args=(north, job))
    thread.start()
    _wait_for(lambda: north.submitted, "north to be submitted")
    south = runner.claim("south", "bbbb", _handle())
    assert south.stage == "queued"
    gate.set()
    thread.join(30)
    runner.release(north, job)
    runner.release(south, None)
    runner.close()


def test_single_key_busy_text_and_errors_kept():
    runner = GoalRunner(_Node(), 0.5, lambda state: state.stage)
    state = runner.claim("", "aaaa", _handle())
    assert runner.claim("", "bbbb", _handle()).endswith("(one calibration at a time)")
    job = EngineJob(lambda j: (_ for _ in ()).throw(ValueError("calibration failed: x")))
    assert runner.run(state, job) == "done"
    assert isinstance(job.error, ValueError) and job.seconds() > 0
    runner.release(state, job)
    assert runner.states() == {} and not isinstance(runner.claim("", "cccc", _handle()), str)
    runner.close()
