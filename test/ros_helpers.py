"""Real ROS 2 processes for tests: an isolated DDS domain per test, logs kept, clean shut-down.

Each test claims a ROS_DOMAIN_ID in 1-101 with a lock file, so tests running at the same time
(pytest-xdist, or two people's test runs on one machine) never hear each other, and DDS traffic
stays on the machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST). Node processes are the installed
console scripts; their output goes to files that are printed when a test fails.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
FASTDDS_PROFILE = REPO / "config" / "fastdds.xml"
LOCK_DIR = Path(tempfile.gettempdir()) / "semcal-ros-domains"


class DomainLock:
    """Holds one free ROS_DOMAIN_ID (1-101) until released."""

    def __init__(self) -> None:
        LOCK_DIR.mkdir(exist_ok=True)
        start = os.getpid() % 101
        for i in range(101):
            domain = (start + i) % 101 + 1
            handle = open(LOCK_DIR / f"{domain}.lock", "w")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                handle.close()
                continue
            self.domain, self._handle = domain, handle
            return
        raise RuntimeError("no free ROS_DOMAIN_ID in 1-101")

    def release(self) -> None:
        fcntl.flock(self._handle, fcntl.LOCK_UN)
        self._handle.close()


def ros_environment(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update({
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(FASTDDS_PROFILE),
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_LOGGING_BUFFERED_STREAM": "0",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "OMP_NUM_THREADS": env.get("OMP_NUM_THREADS", "2"),
    })
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


class RosProcess:
    """One node (or command) process; output in ``log_path``."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str], log_dir: Path) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        self._log = open(self.log_path, "w")
        self.started = time.monotonic()
        self.proc = subprocess.Popen(argv, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                                     cwd=str(REPO))

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def running(self) -> bool:
        return self.proc.poll() is None

    def wait_for_log(self, pattern: str, timeout: float = 30.0) -> re.Match:
        """The first match of ``pattern`` in the output; fails if it exits or times out first."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            match = regex.search(self.log())
            if match:
                return match
            if not self.running():
                raise AssertionError(f"{self.name} exited ({self.proc.returncode}) before "
                                     f"logging /{pattern}/:\n{self.log()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.name}: no /{pattern}/ within {timeout} s:\n"
                                     f"{self.log()}")
            time.sleep(0.05)

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.name} still running after {timeout} s:\n"
                                 f"{self.log()}") from None

    def stop(self, timeout: float = 5.0) -> int:
        """SIGINT (a node's Ctrl-C), then SIGKILL if it does not exit in ``timeout``."""
        if self.running():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode


class RosGraph:
    """The processes of one test in its own domain; :meth:`close` stops them all."""

    def __init__(self, log_dir: Path) -> None:
        self._lock = DomainLock()
        self.domain = self._lock.domain
        self.env = ros_environment(self.domain)
        self.log_dir = log_dir
        self.processes: list[RosProcess] = []

    def start(self, name: str, executable: str, *args: str) -> RosProcess:
        """Start a console script of the venv (``map_builder``, ``semcal`` ...)."""
        argv = [str(BIN / executable), *args]
        proc = RosProcess(name, argv, self.env, self.log_dir)
        self.processes.append(proc)
        return proc

    def start_node(self, executable: str, params: dict | None = None,
                   remap: dict | None = None, params_file: Path | None = None,
                   name: str | None = None) -> RosProcess:
        ros_args = ["--ros-args"]
        if params_file is not None:
            ros_args += ["--params-file", str(params_file)]
        for key, value in (params or {}).items():
            ros_args += ["-p", f"{key}:={_param_text(value)}"]
        for old, new in (remap or {}).items():
            ros_args += ["-r", f"{old}:={new}"]
        return self.start(name or executable, executable, *ros_args)

    def logs(self) -> str:
        return "\n".join(f"----- {p.name} (exit {p.proc.returncode}) -----\n{p.log()}"
                         for p in self.processes)

    def close(self) -> None:
        for proc in reversed(self.processes):
            proc.stop()
        self._lock.release()

    def context(self):
        """An rclpy context in this test's domain, for clients/subscribers inside the test."""
        import rclpy

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=self.domain)
        return ctx


def _param_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_param_text(v) for v in value) + "]"
    return str(value)


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
