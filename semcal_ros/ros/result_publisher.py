"""Where a calibration result goes besides the action's answer: ``calibration/transform``,
``/tf_static`` and the overlay picture (``calibration/overlay``, and ``overlay_file``).

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

try:  # not on PyPI: .ci/setup.d/10-interfaces.sh builds it where it is missing
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None


class ResultPublisher:
    """The calibrator's result publishers (latched) and the transforms kept for /tf_static."""

    def __init__(self, node: Any, publish_tf_static: bool, overlay_file: str = "",
                 overrides: Any = None) -> None:
        self.logger, self.overlay_file = node.get_logger(), overlay_file
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

    def publish(self, transform: TransformStamped, overlay: np.ndarray | None,
                overlay_error: str = "") -> None:
        self.transform_pub.publish(transform)
        if self.tf_pub is not None:
            with self._lock:
                self._tf[transform.child_frame_id] = transform
                every = list(self._tf.values())
            self.tf_pub.publish(TFMessage(transforms=every))
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


__all__ = ["ResultPublisher"]
