"""``image_segmenter``: camera images in, Cityscapes trainId label images out.

Subscribes ``image`` (rgb8/bgr8, sensor-data QoS), runs the user's ONNX model
(:class:`~semcal_ros.segmentation.image.ImageSegmenter`, parameters ``model`` and ``model_config``)
and publishes ``labels`` (mono8 trainIds, 255 = ignored) with the input's header, so the label
image keeps the camera's stamp and frame. Only the newest image is kept while the model runs:
a slow model drops frames rather than falling behind.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

from rclpy.node import Node
from sensor_msgs.msg import Image

from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.diagnostics import Diagnostics, Level
from semcal_ros.ros.latest import LatestWorker, require_model
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import run_node
from semcal_ros.segmentation.onnx_runner import RunnerParams


@dataclass
class ImageSegmenterParams:
    model: str = ""  # ONNX model file (required)
    model_config: str = ""  # its YAML, e.g. config/models/ocrnet_cityscapes.yaml (required)
    queue_size: int = 1  # images waiting while the model runs (the oldest is dropped)
    runner: RunnerParams = field(default_factory=RunnerParams)
    diagnostics_period: float = 1.0  # s (0: off)


class ImageSegmenterNode(Node):
    def __init__(self) -> None:
        super().__init__("image_segmenter")
        from semcal_ros.segmentation.image import ImageSegmenter

        self.opts = declare_and_read(self, ImageSegmenterParams())
        require_model(self.opts.model, self.opts.model_config)
        self.segmenter = ImageSegmenter.from_files(self.opts.model, self.opts.model_config,
                                                   self.opts.runner)
        overrides = qos.overridable()
        self.publisher = self.create_publisher(Image, "labels", qos.sensor(2),
                                               qos_overriding_options=overrides)
        self.worker = LatestWorker(self._segment, self._failed, self.opts.queue_size)
        self.create_subscription(Image, "image", self.worker.put, qos.sensor(2),
                                 qos_overriding_options=overrides)
        self.diagnostics = Diagnostics(self, self._report, self.opts.diagnostics_period)
        self.get_logger().info(f"ready: {self.resolve_topic_name('image')} -> "
                               f"{self.resolve_topic_name('labels')} with {self.opts.model}")

    def close(self) -> None:
        self.worker.stop()

    def _segment(self, msg: Image) -> None:
        rgb = conv.image_to_rgb(msg)  # rgb8 or bgr8 (ValueError names any other encoding)
        labels = self.segmenter.segment(rgb, "rgb8")
        self.publisher.publish(conv.numpy_to_image(labels, "mono8", msg.header))

    def _failed(self, text: str) -> None:
        self.get_logger().error(text, throttle_duration_sec=5.0)

    def _report(self) -> tuple[Level, str, dict[str, Any]]:
        return self.worker.report("images")


def main(args: list[str] | None = None) -> int:
    return run_node(ImageSegmenterNode, threads=2, args=args)


if __name__ == "__main__":
    sys.exit(main())
