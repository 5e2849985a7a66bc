"""A worker thread that processes the newest messages of a stream, dropping what it cannot keep
up with.

Segmentation takes longer than a callback should: done in the subscription callback it would
hold the executor and let DDS queues overflow silently. Callbacks ``put`` messages here instead;
the worker runs ``process`` on them in arrival order, keeps at most ``queue_size`` waiting (the
oldest are dropped and counted) and reports failures by text, so one bad message never stops
the node.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Callable

from semcal_ros.ros.diagnostics import Level


class LatestWorker:
    def __init__(self, process: Callable[[Any], None], report_error: Callable[[str], None],
                 queue_size: int = 1) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, got {queue_size}")
        self.process, self.report_error = process, report_error
        self._queue: deque = deque(maxlen=queue_size)
        self._wake = threading.Condition()
        self._stop = False
        self.received = self.processed = self.dropped = self.failed = 0
        self.last_error = ""
        self.last_seconds = 0.0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def put(self, msg: Any) -> None:
        with self._wake:
            self.received += 1
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append(msg)
            self._wake.notify()

    def stop(self) -> None:
        with self._wake:
            self._stop = True
            self._wake.notify()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._queue and not self._stop:
                    self._wake.wait()
                if self._stop:
                    return
                msg = self._queue.popleft()
            t0 = time.perf_counter()
            try:
                self.process(msg)
                self.processed += 1
            except Exception as exc:  # noqa: BLE001 - a bad message must not stop the node
                self.failed += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                self.report_error(self.last_error)
            self.last_seconds = time.perf_counter() - t0

    def report(self, what: str) -> tuple[Level, str, dict[str, Any]]:
        values = {f"{what}_received": self.received, f"{what}_processed": self.processed,
                  f"{what}_dropped": self.dropped, f"{what}_failed": self.failed,
                  "last_seconds": self.last_seconds, "last_error": self.last_error or "none"}
        if self.failed and self.last_error:
            return Level.ERROR, self.last_error, values
        if self.dropped:
            return Level.WARN, f"{self.dropped} {what} dropped (model slower than input)", values
        return Level.OK, f"{self.processed} {what} segmented", values
