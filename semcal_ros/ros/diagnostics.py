"""Periodic ``/diagnostics`` of a node: one DiagnosticStatus built from a callback.

diagnostic_updater is not on PyPI; what the nodes need from it is small: every ``period`` seconds
ask the node how it is (level, one-line message, key/values) and publish it under the node's name,
so ``rqt_robot_monitor`` or a plain subscriber sees each node's state. A node serving several
cameras adds one status per camera (``parts``), named ``<node>/<camera>`` (hardware_id too), in
the same DiagnosticArray.
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


def status_message(node: Node, level: Level, message: str, values: dict[str, Any],
                   parts: dict[str, Report] | None = None) -> DiagnosticArray:
    """The node's status, then one status per part (``<node>/<part>``)."""
    statuses = [_status(node.get_fully_qualified_name(), node.get_name(), level, message, values)]
    for part, (p_level, p_message, p_values) in (parts or {}).items():
        statuses.append(_status(f"{node.get_fully_qualified_name()}/{part}",
                                f"{node.get_name()}/{part}", p_level, p_message, p_values))
    msg = DiagnosticArray(status=statuses)
    msg.header.stamp = node.get_clock().now().to_msg()
    return msg


def _status(name: str, hardware_id: str, level: Level, message: str, values: dict[str, Any]
            ) -> DiagnosticStatus:
    status = DiagnosticStatus(level=bytes([int(level)]), name=name, message=message,
                              hardware_id=hardware_id)
    status.values = [KeyValue(key=str(k), value=_text(v)) for k, v in values.items()]
    return status


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


class Diagnostics:
    """Publishes ``report()`` (and ``parts()``, one status each) on /diagnostics every ``period``
    seconds (0 disables)."""

    def __init__(self, node: Node, report: Callable[[], Report], period: float = 1.0,
                 callback_group: Any = None,
                 parts: Callable[[], dict[str, Report]] | None = None) -> None:
        self.node, self.report, self.parts = node, report, parts
        self.publisher = node.create_publisher(DiagnosticArray, "/diagnostics", qos.reliable(10))
        self.timer = node.create_timer(period, self.publish, callback_group=callback_group) \
            if period > 0 else None

    def publish(self) -> None:
        level, message, values = self.report()
        parts = self.parts() if self.parts is not None else None
        self.publisher.publish(status_message(self.node, level, message, values, parts))
