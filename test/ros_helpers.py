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

__all__ = ["REPO", "RosGraph", "RosProcess", "publish_until", "spin_until"]


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
