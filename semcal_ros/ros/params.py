"""ROS parameters <-> the library's parameter dataclasses.

Every node's parameters are one dataclass tree (defaults in code, documented there). Its flat,
dotted field names (``mapping.voxel``) are declared as ROS parameters, so a ROS parameter file
(``config/<node>.yaml``) and ``--ros-args -p mapping.voxel:=0.2`` both reach them, and read back
through :func:`semcal_ros.engine.config.apply_flat`, which coerces types and names a bad value. Parameters
are declared with dynamic typing because YAML writes ``2`` for a float field and ``[]`` for an
empty list; the dataclass, not rclpy, decides what is valid.
"""

from __future__ import annotations

from typing import Any, TypeVar

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from semcal_ros.engine.config import apply_flat, dataclass_fields_flat

T = TypeVar("T")


def _ros_value(value: Any) -> Any:
    """A value rclpy can declare: tuples become lists (empty lists stay as they are)."""
    return list(value) if isinstance(value, tuple) else value


def declare_dataclass(node: Node, defaults: Any, prefix: str = "") -> None:
    """Declare one ROS parameter per flat field of the dataclass ``defaults``."""
    for name, value in dataclass_fields_flat(defaults).items():
        node.declare_parameter(prefix + name, _ros_value(value),
                               ParameterDescriptor(dynamic_typing=True))


def read_dataclass(node: Node, defaults: T, prefix: str = "") -> T:
    """The dataclass ``defaults`` with the node's current parameter values applied.

    Raises ValueError naming the parameter whose value does not fit its field (or fails the
    dataclass's own validation).
    """
    flat = {}
    for name in dataclass_fields_flat(defaults):
        value = node.get_parameter(prefix + name).value
        if value is not None:
            flat[name] = value
    try:
        return apply_flat(defaults, flat)
    except ValueError as exc:
        raise ValueError(f"{node.get_name()}: {exc}") from None


def declare_and_read(node: Node, defaults: T, prefix: str = "") -> T:
    declare_dataclass(node, defaults, prefix)
    return read_dataclass(node, defaults, prefix)
