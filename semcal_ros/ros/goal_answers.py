"""How the calibrator answers a ``calibrate`` goal: succeed, abort or cancel, with one message.

What an engine job ended with decides the answer by its type (:mod:`semcal_ros.errors`), never
by its wording:

* :class:`~semcal_ros.errors.Cancelled` — cancelled when the caller asked, else the node is
  shutting down;
* :class:`~semcal_ros.errors.CalibrationFailed` — aborted with its message ("calibration failed:
  ...") and the evaluations and seconds it spent;
* any other ``ValueError`` (input the engine refused) — aborted as "calibration failed: <it>";
* anything else — aborted as an internal error (the job logged its traceback).

Every answer is logged in one line and recorded in the node's status
(:class:`~semcal_ros.ros.calibrator_status.CalibratorStatus`).
"""

from __future__ import annotations

from typing import Any

from semcal_interfaces.action import Calibrate
from semcal_ros.engine.calibration import Calibration
from semcal_ros.errors import CalibrationFailed, Cancelled
from semcal_ros.ros.calibrator_status import CalibratorStatus, result_fields, success_message
from semcal_ros.ros.engine_job import EngineJob, GoalState

PAST = {"succeed": "succeeded", "abort": "aborted", "canceled": "cancelled"}


class GoalAnswers:
    def __init__(self, node: Any, status: CalibratorStatus) -> None:
        self.node, self.status = node, status

    def finish(self, handle: Any, outcome: str, message: str, camera: str | None = None,
               quality: Any = None, **fields: Any) -> Calibrate.Result:
        """Answer ``handle`` (``outcome``: succeed / abort / canceled) with ``message``."""
        result = Calibrate.Result(success=outcome == "succeed", message=message, **fields)
        try:
            getattr(handle, outcome)()
        except Exception:  # noqa: BLE001 - the action server goes away with the node
            if self.node.context.ok():
                raise
            return result
        self.status.record(camera, outcome == "succeed", message, quality)
        logger = self.node.get_logger()
        # rclpy binds a severity to each logging call site: one site per severity, never shared
        if outcome == "succeed":
            logger.info(f"goal {PAST[outcome]}: {message}")
        else:
            logger.warning(f"goal {PAST[outcome]}: {message}")
        return result

    def cancelled(self, handle: Any, job: EngineJob, state: GoalState | None
                  ) -> Calibrate.Result:
        evaluations = state.evaluations if state is not None else 0
        seconds = job.seconds()
        return self.finish(handle, "canceled", f"cancelled after {seconds:.1f} s "
                           f"({evaluations} evaluations reported)", evaluations=evaluations,
                           seconds=seconds)

    def ended(self, handle: Any, job: EngineJob, camera: str, camera_frame: str,
              transform: Any = None, withheld: str = "") -> Calibrate.Result:
        """The answer to a job that ran: its error by type, or its
        :class:`~semcal_ros.engine.calibration.Calibration` with its ``transform`` (published,
        or ``withheld`` says why not: the message ends with it)."""
        exc = job.error
        if isinstance(exc, Cancelled):
            if handle.is_cancel_requested:
                return self.cancelled(handle, job, None)
            return self.finish(handle, "abort", "the calibrator is shutting down")
        if isinstance(exc, CalibrationFailed):
            return self.finish(handle, "abort", str(exc), evaluations=exc.evaluations,
                               seconds=exc.seconds or job.seconds(), camera=camera)
        if isinstance(exc, ValueError):
            return self.finish(handle, "abort", str(CalibrationFailed(str(exc))),
                               seconds=job.seconds(), camera=camera)
        if exc is not None:
            return self.finish(handle, "abort", f"internal error: {type(exc).__name__}: {exc}",
                               seconds=job.seconds(), camera=camera)
        calibration: Calibration = job.result
        result = calibration.result
        q = result.quality
        if q is not None:
            self.node.get_logger().info(f"quality of '{camera_frame}': {q.summary()}")
        message = success_message(result, camera_frame) + (f"; {withheld}" if withheld else "")
        return self.finish(handle, "succeed", message, transform=transform, camera=camera, quality=q,
                           **result_fields(result))


__all__ = ["GoalAnswers"]
