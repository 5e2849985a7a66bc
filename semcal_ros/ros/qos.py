"""The QoS profiles of the nodes, named by what the topic carries.

Streams (scans, images, poses) use sensor-data QoS: best effort, so a subscriber never slows a
sensor down and a late sample is dropped rather than repaired. Best-effort subscribers also accept
reliable publishers (bags, drivers configured either way). Things that exist once and change
rarely (the map, the calibration result, /tf_static) are reliable and transient-local: a node
started later still receives the last one. Publishers and subscriptions are created with QoS
overriding enabled, so history, depth and reliability can be changed by parameters
(``qos_overrides./topic.subscription.depth``) without code changes.
"""

from __future__ import annotations

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rclpy.qos_overriding_options import QoSOverridingOptions


def sensor(depth: int = 5) -> QoSProfile:
    """Best effort, volatile, keep last ``depth``: live sensor streams."""
    profile = QoSProfile(depth=depth)
    profile.history = qos_profile_sensor_data.history
    profile.reliability = qos_profile_sensor_data.reliability
    profile.durability = qos_profile_sensor_data.durability
    return profile


def latched(depth: int = 1) -> QoSProfile:
    """Reliable, transient local, keep last ``depth``: the map, the result, static transforms."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def reliable(depth: int = 10) -> QoSProfile:
    """Reliable, volatile: diagnostics, overlays, /clock."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def overridable() -> QoSOverridingOptions:
    """Let users change history, depth and reliability per topic by parameters."""
    return QoSOverridingOptions.with_default_policies()
