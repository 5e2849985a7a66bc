"""Calling the ``calibrate`` action from Python: goal construction and a blocking call.

Used by ``semcal demo`` and the end-to-end tests; a roadside unit's own code can do the same
(there is no ``ros2 action send_goal`` without the ROS CLI).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from rclpy.node import Node

from semcal_interfaces.action import Calibrate
from semcal_ros.engine.pose import Pose
from semcal_ros.ros import conversions as conv

STATUS_NAMES = {GoalStatus.STATUS_SUCCEEDED: "succeeded", GoalStatus.STATUS_ABORTED: "aborted",
                GoalStatus.STATUS_CANCELED: "canceled", GoalStatus.STATUS_UNKNOWN: "unknown"}


def make_goal(initial: Pose, map_frame: str = "map", camera_frame_id: str = "",
              bound_translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
              bound_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
              verification_starts: int = -1, roll: int = Calibrate.Goal.ROLL_DEFAULT,
              yaw_search: int = Calibrate.Goal.YAW_SEARCH_DEFAULT, loss: str = "",
              seed: int = -1) -> Calibrate.Goal:
    goal = Calibrate.Goal(camera_frame_id=camera_frame_id,
                          verification_starts=verification_starts, roll=roll,
                          yaw_search=yaw_search, loss=loss, seed=seed)
    goal.initial_pose.header.frame_id = map_frame
    goal.initial_pose.pose = conv.pose_to_msg(initial)
    for vec, values in ((goal.bound_translation_m, bound_translation_m),
                        (goal.bound_rpy_deg, bound_rpy_deg)):
        vec.x, vec.y, vec.z = (float(v) for v in values)
    return goal


@dataclass
class CallOutcome:
    accepted: bool
    status: str = ""  # succeeded | aborted | canceled
    result: Any = None  # Calibrate.Result
    feedback: list[tuple[float, Any]] = field(default_factory=list)  # (monotonic time, msg)
    goal_handle: Any = None
    seconds: float = 0.0


class CalibrateClient:
    """Wraps an ActionClient on ``node``; spins the given executor while waiting."""

    def __init__(self, node: Node, action_name: str = "calibrate") -> None:
        self.node = node
        self.client = ActionClient(node, Calibrate, action_name)

    def wait_for_server(self, timeout: float = 15.0) -> None:
        if not self.client.wait_for_server(timeout_sec=timeout):
            raise TimeoutError(f"no '{self.client._action_name}' action server after "
                               f"{timeout:.0f} s (is the calibrator running in this "
                               f"ROS_DOMAIN_ID?)")

    def send(self, executor: Any, goal: Calibrate.Goal, timeout: float = 15.0,
             on_feedback: Callable[[Any], None] | None = None) -> CallOutcome:
        """Send ``goal`` and wait for the server to accept or reject it."""
        outcome = CallOutcome(accepted=False)

        def feedback(msg: Any) -> None:
            outcome.feedback.append((time.monotonic(), msg.feedback))
            if on_feedback is not None:
                on_feedback(msg.feedback)

        future = self.client.send_goal_async(goal, feedback_callback=feedback)
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            raise TimeoutError(f"the action server did not answer the goal in {timeout:.0f} s")
        handle = future.result()
        outcome.accepted, outcome.goal_handle = bool(handle.accepted), handle
        return outcome

    def wait(self, executor: Any, outcome: CallOutcome, timeout: float) -> CallOutcome:
        """Wait for the result of an accepted goal."""
        start = time.monotonic()
        future = outcome.goal_handle.get_result_async()
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            raise TimeoutError(f"no result within {timeout:.0f} s")
        response = future.result()
        outcome.status = STATUS_NAMES.get(response.status, str(response.status))
        outcome.result = response.result
        outcome.seconds = time.monotonic() - start
        return outcome

    def call(self, executor: Any, goal: Calibrate.Goal, timeout: float = 120.0,
             on_feedback: Callable[[Any], None] | None = None) -> CallOutcome:
        outcome = self.send(executor, goal, on_feedback=on_feedback)
        return self.wait(executor, outcome, timeout) if outcome.accepted else outcome

    def cancel(self, executor: Any, outcome: CallOutcome, timeout: float = 10.0) -> Any:
        future = outcome.goal_handle.cancel_goal_async()
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        return future.result()


class DiagnosticsWatcher:
    """The latest /diagnostics key/values of each node (by name), for waiting on a node's state
    (e.g. "the calibrator holds the map of all N scans") without guessing with sleeps."""

    def __init__(self, node: Node) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from semcal_ros.ros import qos

        self.latest: dict[str, dict[str, str]] = {}
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_status,
                                 qos.reliable(50))

    def _on_status(self, msg: Any) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            values["message"], values["level"] = status.message, str(status.level[0])
            self.latest[status.hardware_id] = values

    def get(self, node_name: str) -> dict[str, str]:
        return self.latest.get(node_name, {})

    def wait(self, executor: Any, condition: Callable[[], bool], timeout: float,
             what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                seen = "; ".join(f"{name}: {values}" for name, values in self.latest.items())
                raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what} "
                                   f"(last diagnostics: {seen or 'none'})")
            executor.spin_once(timeout_sec=0.05)

    def map_ready(self, scans: int) -> bool:
        """The map builder published a map of ``scans`` scans and the calibrator holds it."""
        built = self.get("map_builder")
        held = self.get("calibrator")
        return (built.get("map_scans") == str(scans) and built.get("map_points", "0") != "0"
                and held.get("map_points") == built.get("map_points"))
