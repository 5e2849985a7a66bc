"""``image_segmenter``: camera images in, Cityscapes trainId label images out.

Subscribes ``image`` (rgb8/bgr8, sensor-data QoS; with ``image_transport: compressed`` the
CompressedImage stream ``<resolved image topic>/compressed``, JPEG or PNG), runs the user's ONNX
model (:class:`~semcal_ros.segmentation.image.ImageSegmenter`, parameters ``model`` and
``model_config``) and publishes ``labels`` (mono8 trainIds, 255 = ignored) with the input's header, so the label
image keeps the camera's stamp and frame. Only the newest image is kept while the model runs:
a slow model drops frames rather than falling behind. Compressed data that does not decode is
dropped with one WARN naming the topic; the next good message is segmented.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

from sensor_msgs.msg import Image

from semcal_ros.io.images import UndecodableImage
from semcal_ros.ros import compressed
from semcal_ros.ros import conversions as conv
from semcal_ros.ros.runtime import run_node
from semcal_ros.ros.segmenter_node import SegmenterNode
from semcal_ros.segmentation.onnx_runner import RunnerParams


@dataclass
class ImageSegmenterParams:
    model: str = ""  # ONNX model file (required)
    model_config: str = ""  # its YAML, e.g. config/models/ocrnet_cityscapes.yaml (required)
    queue_size: int = 1  # images waiting while the model runs (the oldest is dropped)
    image_transport: str = "raw"  # raw (Image), or compressed (CompressedImage, <image>/compressed)
    runner: RunnerParams = field(default_factory=RunnerParams)
    diagnostics_period: float = 1.0  # s (0: off)

    def __post_init__(self) -> None:
        compressed.check_transport(self.image_transport)


class ImageSegmenterNode(SegmenterNode):
    msg_type, in_topic, out_topic, what = Image, "image", "labels", "images"

    def __init__(self) -> None:
        super().__init__("image_segmenter", ImageSegmenterParams())

    def input(self) -> tuple[Any, str]:
        return compressed.subscription(self, self.in_topic, self.opts.image_transport)

    def load(self, opts: ImageSegmenterParams) -> Any:
        from semcal_ros.segmentation.image import ImageSegmenter

        return ImageSegmenter.from_files(opts.model, opts.model_config, opts.runner)

    def segment_message(self, msg: Any) -> Image | None:
        try:  # rgb8 / bgr8, or JPEG / PNG (ValueError names any other encoding or format)
            rgb = compressed.to_rgb(msg)
        except UndecodableImage as exc:
            # a broken stream warns at most every 5 s, not once per frame
            self.get_logger().warning(f"dropping an image on {self.in_resolved}: {exc}",
                                      throttle_duration_sec=5.0)
            return None
        return conv.numpy_to_image(self.segmenter.segment(rgb, "rgb8"), "mono8", msg.header)


def main(args: list[str] | None = None) -> int:
    return run_node(ImageSegmenterNode, threads=2, args=args)


if __name__ == "__main__":
    sys.exit(main())
