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

from sensor_msgs.msg import Image

from semcal_ros.ros import conversions as conv
from semcal_ros.ros.runtime import run_node
from semcal_ros.ros.segmenter_node import SegmenterNode
from semcal_ros.segmentation.onnx_runner import RunnerParams


@dataclass
class ImageSegmenterParams:
    model: str = ""  # ONNX model file (required)
    model_config: str = ""  # its YAML, e.g. config/models/ocrnet_cityscapes.yaml (required)
    queue_size: int = 1  # images waiting while the model runs (the oldest is dropped)
    runner: RunnerParams = field(default_factory=RunnerParams)
    diagnostics_period: float = 1.0  # s (0: off)


class ImageSegmenterNode(SegmenterNode):
    msg_type, in_topic, out_topic, what = Image, "image", "labels", "images"

    def __init__(self) -> None:
        super().__init__("image_segmenter", ImageSegmenterParams())

    def load(self, opts: ImageSegmenterParams) -> Any:
        from semcal_ros.segmentation.image import ImageSegmenter

        return ImageSegmenter.from_files(opts.model, opts.model_config, opts.runner)

    def segment_message(self, msg: Image) -> Image:
        rgb = conv.image_to_rgb(msg)  # rgb8 or bgr8 (ValueError names any other encoding)
        return conv.numpy_to_image(self.segmenter.segment(rgb, "rgb8"), "mono8", msg.header)


def main(args: list[str] | None = None) -> int:
    return run_node(ImageSegmenterNode, threads=2, args=args)


if __name__ == "__main__":
    sys.exit(main())
