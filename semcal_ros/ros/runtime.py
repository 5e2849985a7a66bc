"""Start-up and shut-down shared by every node's ``main()``.

One place decides how a node process starts (the Fast DDS profile for large messages, rclpy with
the command line's ``--ros-args``), which executor spins it, and how it ends (Ctrl-C / SIGTERM end
quietly with exit code 0; a bad parameter ends with one error line and exit code 1).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Callable

PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def config_file(name: str) -> Path | None:
    """``config/<name>`` of a source checkout, else of the installed package's share."""
    here = Path(__file__).resolve().parents[2] / "config" / name
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory

        shared = Path(get_package_share_directory("semcal_ros")) / "config" / name
        return shared if shared.is_file() else None
    except (LookupError, OSError, ValueError):
        return None


def fastdds_profile() -> Path | None:
    return config_file("fastdds.xml")


def use_default_fastdds_profile() -> None:
    """Point Fast DDS at the project's profile unless the user chose one (or none: set the
    variable to an empty string)."""
    if any(v in os.environ for v in PROFILE_VARIABLES):
        return
    profile = fastdds_profile()
    if profile is not None:
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)


def release_free_memory() -> None:
    """Hand the heap's free pages back to the system (glibc ``malloc_trim``; nothing elsewhere).

    After a large, short-lived working set (a goal's prepared map and render buffers) glibc keeps
    the freed pages in its arenas, and RSS stays at the high-water mark of every arena; nodes call
    this when such a piece of work has ended.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def run_node(make_node: Callable[[], "object"], threads: int | Callable[[Any], int] = 1,
             args: list[str] | None = None) -> int:
    """Init rclpy, build the node, spin it until shut down; the process exit code. ``threads``
    of the executor may depend on the node (a callable given the built node)."""
    import rclpy
    from rclpy.executors import (ExternalShutdownException, MultiThreadedExecutor,
                                 SingleThreadedExecutor)

    use_default_fastdds_profile()
    rclpy.init(args=sys.argv if args is None else args)
    node = None
    try:
        try:
            node = make_node()
        except (ValueError, FileNotFoundError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        if callable(threads):
            threads = threads(node)
        executor = MultiThreadedExecutor(threads) if threads > 1 else SingleThreadedExecutor()
        executor.add_node(node)
        try:
            executor.spin()
        except Exception:  # noqa: BLE001 - rclpy raises its own RCLError at Ctrl-C
            # SIGINT can invalidate the context while the executor waits ("failed to initialize
            # wait set: the given context is not valid"): that is the shutdown, not a failure
            if rclpy.ok():
                raise
        finally:
            executor.shutdown(timeout_sec=1.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
