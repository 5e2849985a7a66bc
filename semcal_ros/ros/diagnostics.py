"""Periodic ``/diagnostics`` of a node: one DiagnosticStatus built from a callback.

diagnostic_updater is not on PyPI; what the nodes need from it is small: every ``period`` seconds
ask the node how it is (level, one-line message, key/values) and publish it under the node's name,
so ``rqt_robot_monitor`` or a plain subscriber sees each node's state.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from semcal_ros.ros import qos


class Level(IntEnum):
    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


Report = tuple[Level, str, dict[str, Any]]


def status_message(node: Node, level: Level, message: str, values: dict[str, Any]
                   ) -> DiagnosticArray:
    status = DiagnosticStatus(level=bytes([int(level)]), name=node.get_fully_qualified_name(),
                              message=message, hardware_id=node.get_name())
    status.values = [KeyValue(key=str(k), value=_text(v)) for k, v in values.items()]
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = node.get_clock().now().to_msg()
    return msg


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


class Diagnostics:
    """Publishes ``report()`` on /diagnostics every ``period`` seconds (0 disables)."""

    def __init__(self, node: Node, report: Callable[[], Report], period: float = 1.0,
                 callback_group: Any = None) -> None:
        self.node, self.report = node, report
        self.publisher = node.create_publisher(DiagnosticArray, "/diagnostics", qos.reliable(10))
        self.timer = node.create_timer(period, self.publish, callback_group=callback_group) \
            if period > 0 else None

    def publish(self) -> None:
        level, message, values = self.report()
        self.publisher.publish(status_message(self.node, level, message, values))
