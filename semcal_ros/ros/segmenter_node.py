"""The shape both segmenter nodes share: one input topic, a model, one output topic.

Parameters come from a dataclass with ``model``, ``model_config``, ``queue_size``, ``runner`` and
``diagnostics_period``; the model is loaded once at start (a missing file stops the node with a
message naming the parameter); messages are segmented by a :class:`LatestWorker` so the executor
never waits for the model; the worker's counts are the node's diagnostics.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rclpy.node import Node

from semcal_ros.ros import qos
from semcal_ros.ros.diagnostics import Diagnostics
from semcal_ros.ros.latest import LatestWorker
from semcal_ros.ros.params import declare_and_read


def require_model(model: str, config: str) -> None:
    """Refuse to start a segmenter without its model files (clear message naming the parameter)."""
    if not model or not config:
        raise ValueError("parameters 'model' (ONNX file) and 'model_config' (YAML) are required")
    for name, path in (("model", model), ("model_config", config)):
        if not Path(path).is_file():
            raise FileNotFoundError(f"parameter '{name}': file not found: {path}")


class SegmenterNode(Node):
    """Subclasses set ``msg_type``, ``in_topic``, ``out_topic``, ``what`` and implement
    :meth:`load` and :meth:`segment_message`."""

    msg_type: Any = None
    in_topic, out_topic, what = "in", "out", "messages"

    def __init__(self, name: str, defaults: Any) -> None:
        super().__init__(name)
        self.opts = declare_and_read(self, defaults)
        self.require(self.opts)
        try:
            self.segmenter = self.load(self.opts)
        except (ValueError, FileNotFoundError):
            raise
        except Exception as exc:  # onnxruntime's own errors: one line, naming the parameter
            first = (str(exc).strip().splitlines() or [""])[0]
            raise ValueError(f"parameter 'model': cannot load {self.opts.model} "
                             f"({type(exc).__name__}: {first})") from None
        overrides = qos.overridable()
        depth = max(self.opts.queue_size, 2)
        self.publisher = self.create_publisher(self.msg_type, self.out_topic, qos.sensor(depth),
                                               qos_overriding_options=overrides)
        self.create_outputs(depth, overrides)
        self._last_failure = ""
        self.worker = LatestWorker(self._process, self._failed, self.opts.queue_size)
        in_type, self.in_resolved = self.input()
        self.create_subscription(in_type, self.in_resolved, self.worker.put, qos.sensor(depth),
                                 qos_overriding_options=overrides)
        self.diagnostics = Diagnostics(self, lambda: self.worker.report(self.what),
                                       self.opts.diagnostics_period)
        self.get_logger().info(f"ready: {self.resolve_topic_name(self.in_resolved)} -> "
                               f"{self.resolve_topic_name(self.out_topic)} with "
                               f"{self.opts.model}")

    def input(self) -> tuple[Any, str]:
        """(message type, topic) of the input; the image segmenter's depends on its
        ``image_transport``."""
        return self.msg_type, self.in_topic

    def create_outputs(self, depth: int, overrides: Any) -> None:
        """More publishers beside ``out_topic`` (made before the subscription, so the first
        message finds them); default none."""

    def require(self, opts: Any) -> None:
        """Refuse to start without what :meth:`load` needs (default: the model files)."""
        require_model(opts.model, opts.model_config)

    def load(self, opts: Any) -> Any:
        raise NotImplementedError

    def segment_message(self, msg: Any) -> Any:
        raise NotImplementedError

    def close(self) -> None:
        self.worker.stop()

    def _process(self, msg: Any) -> None:
        out = self.segment_message(msg)
        if out is not None:  # None: the message was dropped (and said so)
            self.publisher.publish(out)

    def _failed(self, text: str) -> None:
        """A new problem is always logged; the same one again at most every 5 s (a throttle
        alone hid a second, different problem for 5 s)."""
        if text != self._last_failure:
            self._last_failure = text
            self.get_logger().error(text)
        else:
            self.get_logger().error(text, throttle_duration_sec=5.0)
