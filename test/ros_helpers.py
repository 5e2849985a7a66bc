"""Real ROS 2 processes for tests: an isolated DDS domain per test, logs kept, clean shut-down.

Each test's :class:`RosGraph` claims a ROS_DOMAIN_ID in 1-101 with a lock file, so tests running
at the same time (pytest-xdist, or two people's test runs on one machine) never hear each other,
and DDS traffic stays on the machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST). Node processes
are the installed console scripts; their output goes to files that the fixtures print when a test
fails. The machinery is :mod:`semcal_tools.launch`, which ``semcal demo`` uses too.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from semcal_tools.launch import NodeGraph as RosGraph
from semcal_tools.launch import NodeProcess as RosProcess

REPO = Path(__file__).resolve().parents[1]

__all__ = ["HELD_STARTS", "REPO", "RosGraph", "RosProcess", "held_goal", "publish_until",
           "reliable_overrides", "spin_until"]

#: Verification starts of a goal that runs until the test cancels it: each start is a coarse
#: search of its own (tens of renders, a millisecond each at the very least), so this many keep
#: the engine busy for several minutes on any machine, far beyond what a test holds it for.
#: Tests that need "a goal still running" hold one of these instead of hoping that a cheap goal
#: has not finished yet.
HELD_STARTS = 10_000


def held_goal(initial, **options):
    """A calibrate goal from ``initial`` that stays running until it is cancelled."""
    from semcal_ros.ros.client import make_goal

    return make_goal(initial, verification_starts=HELD_STARTS, **options)


def spin_until(executor, condition: Callable[[], bool], timeout: float,
               what: str = "condition") -> None:
    """Spin ``executor`` until ``condition()``; AssertionError naming ``what`` on timeout."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        executor.spin_once(timeout_sec=0.05)


def publish_until(executor, publisher, msg, condition: Callable[[], bool], timeout: float,
                  what: str = "a reply", period: float = 0.3) -> None:
    """Publish ``msg`` every ``period`` s (discovery takes a moment) until ``condition()``."""
    deadline = time.monotonic() + timeout
    next_publish = 0.0
    while not condition():
        now = time.monotonic()
        if now > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        if now >= next_publish:
            publisher.publish(msg)
            next_publish = now + period
        executor.spin_once(timeout_sec=0.05)


def reliable_overrides(*topics: str, depth: int = 100) -> dict[str, object]:
    """QoS override parameters that make a node's subscriptions to ``topics`` (resolved names)
    reliable with room for ``depth`` messages: what a user sets for a replay that must lose
    nothing, and what a test sets when it counts every message (best effort may drop one when
    the machine is loaded)."""
    out: dict[str, object] = {}
    for topic in topics:
        out[f"qos_overrides.{topic}.subscription.reliability"] = "reliable"
        out[f"qos_overrides.{topic}.subscription.depth"] = depth
    return out
