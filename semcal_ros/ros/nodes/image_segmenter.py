"""``image_segmenter``: camera images in, Cityscapes trainId label images out.

Subscribes ``image`` (rgb8/bgr8, sensor-data QoS; with ``image_transport: compressed`` the
CompressedImage stream ``<resolved image topic>/compressed``, JPEG or PNG), runs the user's ONNX
model (:class:`~semcal_ros.segmentation.image.ImageSegmenter`, parameters ``model`` and
``model_config``) and publishes ``labels`` (mono8 trainIds, 255 = ignored) with the input's
header, so the label image keeps the camera's stamp and frame. With ``publish_probabilities:
true`` it also publishes ``label_probabilities``: the class probabilities (trainIds 0-18,
pixel-aligned with the labels) as an ``8UC19`` Image (probability x 255, rounded) with the same
header, just before the labels (docs/CONTRACTS.md). Only the newest image is kept while the model
runs: a slow model drops frames rather than falling behind. Compressed data that does not decode is
dropped with one WARN naming the topic; the next good message is segmented.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from semcal_ros.io.images import UndecodableImage
from semcal_ros.ros import compressed, qos
from semcal_ros.ros import conversions as conv
from semcal_ros.ros.runtime import run_node
from semcal_ros.ros.segmenter_node import SegmenterNode
from semcal_ros.segmentation import probabilities as probs_format
from semcal_ros.segmentation.onnx_runner import RunnerParams


@dataclass
class ImageSegmenterParams:
    model: str = ""  # ONNX model file (required)
    model_config: str = ""  # its YAML, e.g. config/models/ocrnet_cityscapes.yaml (required)
    queue_size: int = 1  # images waiting while the model runs (the oldest is dropped)
    image_transport: str = "raw"  # raw (Image), or compressed (CompressedImage, <image>/compressed)
    publish_probabilities: bool = False  # also label_probabilities (8UC19), for a loss on them
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

    def create_outputs(self, depth: int, overrides: Any) -> None:
        self.probabilities_publisher = None
        if self.opts.publish_probabilities:
            self.probabilities_publisher = self.create_publisher(
                Image, "label_probabilities", qos.sensor(depth),
                qos_overriding_options=overrides)

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
        if self.probabilities_publisher is None:
            labels = self.segmenter.segment(rgb, "rgb8")
        else:  # probabilities first: whoever gets the labels finds them already there
            labels, probabilities = self.segmenter.segment_with_probabilities(rgb, "rgb8")
            self.probabilities_publisher.publish(probabilities_to_image(probabilities,
                                                                        msg.header))
        return conv.numpy_to_image(labels, "mono8", msg.header)


def probabilities_to_image(probabilities: np.ndarray, header: Header) -> Image:
    """(H, W, 19) probabilities -> ``8UC19`` Image: probability x 255, rounded."""
    data = probs_format.to_bytes(probabilities)
    height, width, channels = data.shape
    out = Image(header=header, height=height, width=width, encoding=probs_format.ROS_ENCODING,
                is_bigendian=0, step=width * channels)
    out.data = np.ascontiguousarray(data).tobytes()
    return out


def image_to_probabilities(msg: Image) -> np.ndarray:
    """(H, W, 19) float32 probabilities of an ``8UC19`` Image (ValueError for anything else)."""
    n = probs_format.NUM_TRAIN_IDS
    if msg.encoding != probs_format.ROS_ENCODING or msg.step != msg.width * n:
        raise ValueError(f"expected a {probs_format.ROS_ENCODING} image with step = 19 x width, "
                         f"got encoding '{msg.encoding}', step {msg.step} for width "
                         f"{msg.width}")
    data = np.frombuffer(msg.data, np.uint8)
    if data.size != msg.height * msg.width * n:
        raise ValueError(f"{probs_format.ROS_ENCODING} image of {msg.width}x{msg.height} holds "
                         f"{data.size} bytes, expected {msg.height * msg.width * n}")
    return probs_format.from_bytes(data.reshape(msg.height, msg.width, n))


def main(args: list[str] | None = None) -> int:
    return run_node(ImageSegmenterNode, threads=2, args=args)


if __name__ == "__main__":
    sys.exit(main())
