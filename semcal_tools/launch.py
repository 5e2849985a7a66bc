"""Starting node processes without ``ros2 launch`` (not on PyPI): for ``semcal demo`` and tests.

A :class:`NodeGraph` claims a free ROS_DOMAIN_ID (1-101, by lock file, so two demos or test runs
on one machine never hear each other), keeps DDS traffic on the machine
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), starts the venv's node executables with
``--ros-args``, sends their output to log files and stops them with SIGINT (a node's Ctrl-C).
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
from typing import Any

from semcal_ros.ros.runtime import fastdds_profile

BIN = Path(sys.executable).parent
LOCK_DIR = Path(tempfile.gettempdir()) / "semcal-ros-domains"


class DomainLock:
    """Holds one free ROS_DOMAIN_ID (1-101: higher ids give port numbers beyond the valid range)
    until released."""

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
    """This process's environment for a node in ``domain``, traffic kept on the machine unless
    the caller's environment already chose a discovery range (two hosts: SUBNET and
    ROS_STATIC_PEERS, docs/two-hosts.md)."""
    env = dict(os.environ)
    env.update({"ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1",
                "RCUTILS_LOGGING_BUFFERED_STREAM": "0", "RCUTILS_COLORIZED_OUTPUT": "0"})
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    profile = fastdds_profile()
    if profile is not None:
        env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(profile))
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def ros_args(params: dict[str, Any] | None = None, remap: dict[str, str] | None = None,
             params_file: str | Path | None = None) -> list[str]:
    out = ["--ros-args"]
    if params_file is not None:
        out += ["--params-file", str(params_file)]
    for key, value in (params or {}).items():
        out += ["-p", f"{key}:={param_text(value)}"]
    for old, new in (remap or {}).items():
        out += ["-r", f"{old}:={new}"]
    return out


def param_text(value: Any) -> str:
    """A value as ``-p name:=value`` wants it (YAML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(param_text(v) for v in value) + "]"
    return str(value)


class NodeProcess:
    """One node (or command) process; output in ``log_path``."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str], log_dir: Path) -> None:
        self.name = name
        self.log_path = Path(log_dir) / f"{name}.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(argv, env=env, stdout=self._log, stderr=subprocess.STDOUT)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def running(self) -> bool:
        return self.proc.poll() is None

    def wait_for_log(self, pattern: str, timeout: float = 30.0) -> re.Match:
        """The first match of ``pattern`` in the output; TimeoutError/RuntimeError (with the
        log) if it times out or the process exits first."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            match = regex.search(self.log())
            if match:
                return match
            if not self.running():
                raise RuntimeError(f"{self.name} exited ({self.proc.returncode}) before "
                                   f"logging /{pattern}/:\n{self.log()}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.name}: no /{pattern}/ within {timeout} s:\n"
                                   f"{self.log()}")
            time.sleep(0.05)

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"{self.name} still running after {timeout} s:\n"
                               f"{self.log()}") from None

    def stop(self, timeout: float = 5.0) -> int:
        """SIGINT, then SIGKILL if it does not exit in ``timeout``."""
        if self.running():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode


class NodeGraph:
    """The processes of one demo or test in a domain of its own; :meth:`close` (or leaving a
    ``with`` block) stops them."""

    def __init__(self, log_dir: str | Path) -> None:
        self._lock = DomainLock()
        self.domain = self._lock.domain
        self.env = ros_environment(self.domain)
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.processes: list[NodeProcess] = []
        self.contexts: list[Any] = []

    def __enter__(self) -> "NodeGraph":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def start(self, name: str, executable: str, *args: str) -> NodeProcess:
        """Start a console script of the venv (``map_builder``, ``semcal`` ...)."""
        proc = NodeProcess(name, [str(BIN / executable), *args], self.env, self.log_dir)
        self.processes.append(proc)
        return proc

    def start_node(self, executable: str, params: dict | None = None,
                   remap: dict | None = None, params_file: str | Path | None = None,
                   name: str | None = None) -> NodeProcess:
        return self.start(name or executable, executable,
                          *ros_args(params, remap, params_file))

    def logs(self) -> str:
        return "\n".join(f"----- {p.name} (exit {p.proc.returncode}) -----\n{p.log()}"
                         for p in self.processes)

    def context(self) -> Any:
        """An rclpy context in this graph's domain, for a client inside this process."""
        import rclpy

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        profile = fastdds_profile()
        if profile is not None:
            os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(profile))
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=self.domain)
        self.contexts.append(ctx)
        return ctx

    def close(self) -> None:
        """Shut the contexts made by :meth:`context` down, stop every process, free the domain."""
        for ctx in self.contexts:
            ctx.try_shutdown()
        for proc in reversed(self.processes):
            proc.stop()
        self._lock.release()
