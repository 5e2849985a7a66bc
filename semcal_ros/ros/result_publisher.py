"""Where a calibration result goes besides the action's answer: ``calibration/transform``,
``/tf_static`` and the overlay picture (``calibration/overlay``, and ``overlay_file``).

Only a result whose verdict is in ``publish_verdicts`` (the calibrator's parameter; default good
and inconclusive) goes to ``calibration/transform`` and ``/tf_static``: a failed result would
otherwise replace a good transform that every consumer of the camera's frame uses, so the held
one stays (the action result still carries the failed pose with its verdict). The overlay of
every result is published: it shows the verdict and is how one sees why a result failed.

``/tf_static`` holds one TFMessage with the newest transform of every camera calibrated so far
(as tf2's static broadcaster does: a latched topic keeps only the last message, so each message
must carry them all). The overlay is a by-product: when drawing it failed, or the file cannot be
written, that is logged and the result stands.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import Image

from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos

#: The verdicts published by default (``publish_verdicts``): a failed result is not.
DEFAULT_PUBLISH_VERDICTS = ("good", "inconclusive")

try:  # not on PyPI: .ci/setup.d/10-interfaces.sh builds it where it is missing
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None


class ResultPublisher:
    """The calibrator's result publishers (latched) and the transforms kept for /tf_static."""

    def __init__(self, node: Any, publish_tf_static: bool, overlay_file: str = "",
                 overrides: Any = None,
                 publish_verdicts: tuple[str, ...] = DEFAULT_PUBLISH_VERDICTS) -> None:
        self.logger, self.overlay_file = node.get_logger(), overlay_file
        self.publish_verdicts = tuple(publish_verdicts)
        self.transform_pub = node.create_publisher(
            TransformStamped, "calibration/transform", qos.latched(),
            qos_overriding_options=overrides)
        self.overlay_pub = node.create_publisher(Image, "calibration/overlay", qos.latched(),
                                                 qos_overriding_options=overrides)
        self.tf_pub = None
        if publish_tf_static:
            if TFMessage is None:
                self.logger.warning("tf2_msgs is not installed: the result is published on "
                                    "calibration/transform only (not on /tf_static)")
            else:
                self.tf_pub = node.create_publisher(TFMessage, "/tf_static", qos.latched())
        self._lock = threading.Lock()
        self._tf: dict[str, TransformStamped] = {}  # child frame -> its latest transform

    def publishes(self, verdict: str | None) -> bool:
        """Whether a result of ``verdict`` goes to the transform topics (None: a result without
        a quality report, which has no verdict to refuse)."""
        return verdict is None or verdict in self.publish_verdicts

    def withheld(self, verdict: str | None) -> str:
        """Why a result of ``verdict`` is not published ("" when it is)."""
        if self.publishes(verdict):
            return ""
        allowed = ", ".join(self.publish_verdicts) or "none"
        return (f"not published on /tf_static or calibration/transform: verdict {verdict} "
                f"(publish_verdicts: {allowed}); the transform held before stays")

    def publish(self, transform: TransformStamped, overlay: np.ndarray | None,
                overlay_error: str = "", verdict: str | None = None) -> bool:
        """Publish a result (the transform only if :meth:`publishes` its verdict); whether the
        transform was published."""
        published = self.publishes(verdict)
        if published:
            self.transform_pub.publish(transform)
        else:
            self.logger.warning(f"result of '{transform.child_frame_id}' "
                                f"{self.withheld(verdict)}")
        if published and self.tf_pub is not None:
            with self._lock:
                self._tf[transform.child_frame_id] = transform
                every = list(self._tf.values())
            self.tf_pub.publish(TFMessage(transforms=every))
        self._overlay(transform, overlay, overlay_error)
        return published

    def _overlay(self, transform: TransformStamped, overlay: np.ndarray | None,
                 overlay_error: str) -> None:
        if overlay is None:
            self.logger.error(f"overlay failed: {overlay_error}")
            return
        self.overlay_pub.publish(conv.numpy_to_image(
            np.ascontiguousarray(overlay, np.uint8), "rgb8",
            conv.make_header(transform.child_frame_id, transform.header.stamp)))
        if self.overlay_file:
            from semcal_ros.io.files import write_rgb_image

            try:
                write_rgb_image(self.overlay_file, overlay)
                self.logger.info(f"overlay written to {self.overlay_file}")
            except OSError as exc:
                self.logger.error(f"overlay not written: {exc}")


__all__ = ["DEFAULT_PUBLISH_VERDICTS", "ResultPublisher"]
