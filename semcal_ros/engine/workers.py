"""Independent work side by side on the cores: the frames of a rig, the coarse stage of the
verification starts, the evidence's parts.

Why not the renderer's own thread pool for everything: a render splits its chunks over the
cores and merges one z-buffer per thread, and at 1/4 resolution that costs as much as it
saves (bench street 1 M: 0.81 ms on two threads against 1.0 ms on one, 1.6 ms of CPU against
1.0). Searches that do not depend on each other gain more from running one per core, each
rendering on its own thread (the renderer and the losses release the GIL): the same
arithmetic, so the same results, in less wall time and less CPU.

A render made on one of these workers draws on the worker's thread (:func:`render_threads`), and
work handed to :func:`side_by_side` from a worker runs there in order: the pool never waits on
itself.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Callable, Iterable, TypeVar

import numba

T = TypeVar("T")
R = TypeVar("R")

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
_LOCAL = threading.local()


def _pool() -> ThreadPoolExecutor | None:
    """The process's workers: one per numba thread, made on first use and shared by every
    caller; None with a single thread."""
    global _POOL
    workers = numba.get_num_threads()
    if workers < 2:
        return None
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="semcal-worker")
        return _POOL


def on_worker() -> bool:
    """True on one of the workers (inside a :func:`side_by_side` call)."""
    return getattr(_LOCAL, "inside", False)


def render_threads() -> int | None:
    """The renderer's thread count for a render made here: 1 on a worker (the other cores run
    the other workers), None (the renderer's pool) elsewhere."""
    return 1 if on_worker() else None


def side_by_side(call: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``call(item)`` for every item, the results in the items' order: on the workers when
    there are several items and several cores and this is not already a worker, else one after
    another here. The calls must not share state they change. When one raises (a cancelled
    goal: :class:`~semcal_ros.errors.Cancelled`), the items not yet begun are not begun, the
    running ones are waited for (each stops at its next check), and the first exception in
    the items' order is raised: nothing of the call runs on after it returns."""
    items = list(items)
    pool = None if len(items) < 2 or on_worker() else _pool()
    if pool is None:
        return [call(item) for item in items]
    failed = threading.Event()

    def run(item: T) -> R | None:
        if failed.is_set():
            return None
        _LOCAL.inside = True
        try:
            return call(item)
        except BaseException:
            failed.set()
            raise
        finally:
            _LOCAL.inside = False

    futures = [pool.submit(run, item) for item in items]
    wait(futures)
    for f in futures:
        error = f.exception()
        if error is not None:
            raise error
    return [f.result() for f in futures]  # type: ignore[misc]  # none skipped: none failed


__all__ = ["on_worker", "render_threads", "side_by_side"]
