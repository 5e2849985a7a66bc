"""An engine call as an action goal: one long-lived engine thread, goals queued on it, one goal
per key (camera) at a time, cancel answered at once, feedback on a timer.

Why each piece:

* One long-lived thread runs every job (:class:`EngineWorker`). A thread per goal made RSS grow
  from goal to goal (465 -> 667 MB over 25 cheap goals): glibc gives a new thread a malloc arena
  of its own, and each arena kept the high-water mark of the goal that used it. One thread reuses
  one arena, and after each job the freed memory is handed back (:func:`release_free_memory`).
* Jobs run one after another in arrival order (two cores: two engines side by side would each run
  at half speed and hold two working sets). A job waiting for its turn is "queued".
* One goal per key (:class:`GoalRunner`): a second goal for a key that is running or queued is
  refused with the reason (the action protocol's rejection carries none, so the node accepts and
  aborts it with this text).
* A cancel is answered at once, even while the engine is in a step that checks for it only at its
  end; the engine stops at its next check and until then the key counts as busy ("stopping").
  A job cancelled while still queued never starts.
* Feedback: a timer sends each goal's state (stage, evaluations, best loss and pose) at least once
  a second, from the executor, never from the engine thread.
"""

from __future__ import annotations

import math
import queue
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable

from semcal_ros.engine.pose import Pose
from semcal_ros.errors import Cancelled
from semcal_ros.ros.runtime import release_free_memory


class JobCancelled(Cancelled):
    """A job stopped before it started (cancelled while queued, or the node is shutting down)."""


class EngineJob:
    """One piece of engine work: ``work(job)`` runs on the engine thread; its return value or
    exception is kept. ``work`` polls :meth:`should_stop` (the engine's ``should_stop``)."""

    def __init__(self, work: Callable[["EngineJob"], Any],
                 stop_also: Callable[[], bool] | None = None,
                 log_error: Callable[[str], None] | None = None) -> None:
        self.work, self._stop_also, self._log_error = work, stop_also, log_error
        self.result: Any = None
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.stop = threading.Event()  # set once the goal is answered as cancelled / aborted
        self.started: float | None = None  # perf_counter when the engine thread took it
        self.on_start: Callable[[], None] | None = None
        self.on_end: Callable[["EngineJob"], None] | None = None

    def seconds(self) -> float:
        return 0.0 if self.started is None else time.perf_counter() - self.started

    def should_stop(self) -> bool:
        return self.stop.is_set() or (self._stop_also is not None and self._stop_also())

    def run(self) -> None:
        try:
            if self.should_stop():
                raise JobCancelled("cancelled before it started")
            self.started = time.perf_counter()
            if self.on_start is not None:
                self.on_start()
            self.result = self.work(self)
        except Exception as exc:  # noqa: BLE001 - the caller reports it as the goal's result
            # expected endings (bad input, a failed or cancelled calibration) are answers; only
            # the unexpected get a traceback in the log
            if self._log_error is not None and not isinstance(exc, (ValueError, Cancelled)):
                self._log_error(traceback.format_exc())
            self.error = exc
        finally:
            self.done.set()
            if self.on_end is not None:
                self.on_end(self)


class EngineWorker:
    """The one thread that runs every job, in arrival order, for the life of the node."""

    def __init__(self, name: str = "engine") -> None:
        self._jobs: queue.Queue[EngineJob | None] = queue.Queue()
        self.thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self.thread.start()

    def submit(self, job: EngineJob) -> None:
        self._jobs.put(job)

    def pending(self) -> int:
        """Jobs waiting for the thread (not counting the one it runs)."""
        return self._jobs.qsize()

    def close(self) -> None:
        self._jobs.put(None)

    def _loop(self) -> None:
        while (job := self._jobs.get()) is not None:
            job.run()
            job = None  # nothing of the goal (inputs, result, history) outlives it here
            release_free_memory()


@dataclass
class GoalState:
    """A goal of one key, from acceptance to its answer (or, after a cancel, to the engine's
    stop)."""

    key: str
    goal_id: str
    handle: Any
    accepted: float  # monotonic
    stage: str = "preparing"  # "queued" while other goals' jobs are ahead of it
    evaluations: int = 0
    best_loss: float = math.inf
    best_pose: Pose | None = None
    submitted: bool = False
    running: bool = False

    def progress(self, p: Any) -> None:
        """An engine :class:`~semcal_ros.engine.results.Progress` report."""
        self.stage, self.evaluations = p.stage, p.evaluations
        self.best_loss, self.best_pose = p.best_loss, p.best_pose


class GoalRunner:
    """Goals of an action server run as :class:`EngineJob` on one :class:`EngineWorker`; at most
    one goal per key. ``make_feedback(state)`` builds the action's feedback message."""

    def __init__(self, node: Any, feedback_period: float,
                 make_feedback: Callable[[GoalState], Any], callback_group: Any = None,
                 worker_name: str = "engine") -> None:
        self.node = node
        self.make_feedback = make_feedback
        self.worker = EngineWorker(worker_name)
        self._lock = threading.Lock()
        self._goals: dict[str, GoalState] = {}
        self.last_rejection = ""
        self.timer = node.create_timer(feedback_period, self._send_feedback,
                                       callback_group=callback_group)

    # --- bookkeeping ------------------------------------------------------------------------
    def claim(self, key: str, goal_id: str, handle: Any) -> GoalState | str:
        """A new goal for ``key``: its state, or the reason it cannot be taken (busy)."""
        with self._lock:
            held = self._goals.get(key)
            if held is not None:
                age = time.monotonic() - held.accepted
                whose = f" for camera '{key}'" if key else ""
                note = "one calibration per camera at a time" if key else \
                    "one calibration at a time"
                if held.stage != "queued":
                    self.last_rejection = (f"busy: goal {held.goal_id}{whose} has been running "
                                           f"for {age:.1f} s, now '{held.stage}' ({note})")
                else:
                    self.last_rejection = (f"busy: goal {held.goal_id}{whose} is queued "
                                           f"({age:.1f} s, behind the goals of other cameras) "
                                           f"({note})")
                return self.last_rejection
            state = GoalState(key, goal_id, handle, time.monotonic())
            if any(s.submitted for s in self._goals.values()):
                state.stage = "queued"  # from its first feedback on, not once it is submitted
            self._goals[key] = state
            self.last_rejection = ""
            return state

    def states(self) -> dict[str, GoalState]:
        with self._lock:
            return dict(self._goals)

    def state(self, key: str) -> GoalState | None:
        with self._lock:
            return self._goals.get(key)

    def progress(self, state: GoalState, p: Any) -> None:
        with self._lock:
            state.progress(p)

    # --- running ----------------------------------------------------------------------------
    def run(self, state: GoalState, job: EngineJob) -> str:
        """Submit ``job`` for ``state`` and wait: "done", "cancelled" (answer the goal as
        cancelled now) or "shutdown". Call :meth:`release` afterwards in any case."""
        def started() -> None:
            with self._lock:
                state.running, state.stage = True, "preparing"

        def ended(finished: EngineJob) -> None:
            with self._lock:
                if getattr(finished, "release_on_exit", False):
                    self._drop(state)

        job.on_start, job.on_end = started, ended
        job.release_on_exit = False  # type: ignore[attr-defined]
        with self._lock:
            ahead = sum(1 for s in self._goals.values() if s.submitted and s is not state)
            state.submitted = True
            if ahead and not state.running:
                state.stage = "queued"
        self.worker.submit(job)
        handle = state.handle
        while not job.done.wait(0.05):
            if handle.is_cancel_requested or not self.node.context.ok():
                job.stop.set()
                return "cancelled" if handle.is_cancel_requested else "shutdown"
        return "done"

    def release(self, state: GoalState, job: EngineJob | None) -> None:
        """The goal is answered: free its key now, or (engine still stopping) when its job
        ends."""
        with self._lock:
            state.handle = None
            if job is None or job.done.is_set():
                self._drop(state)
            else:
                job.release_on_exit = True  # type: ignore[attr-defined]
                state.stage = "stopping (answered)"

    def _drop(self, state: GoalState) -> None:
        """(under the lock)"""
        if self._goals.get(state.key) is state:
            del self._goals[state.key]

    def close(self) -> None:
        self.worker.close()

    def _send_feedback(self) -> None:
        with self._lock:
            pending = [(s.handle, self.make_feedback(s)) for s in self._goals.values()
                       if s.handle is not None]
        for handle, feedback in pending:
            try:
                handle.publish_feedback(feedback)
            except Exception as exc:  # noqa: BLE001 - the goal may finish between lock and publish
                self.node.get_logger().debug(f"feedback not sent: {exc}")


__all__ = ["EngineJob", "EngineWorker", "GoalRunner", "GoalState", "JobCancelled"]
