"""The ``image_transport`` parameter of node inputs that take images: ``raw`` or ``compressed``.

image_transport names a compressed stream ``<base topic>/compressed`` after the *resolved* base
topic, so a node resolves its relative image topic with its remappings first
(``-r image:=/cam/image_raw`` -> ``/cam/image_raw/compressed``) and subscribes
``sensor_msgs/CompressedImage`` there. Decoding is :mod:`semcal_ros.io.images` (no ROS).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import CompressedImage, Image

from semcal_ros.io import images
from semcal_ros.ros import conversions as conv

#: The values of an ``image_transport`` parameter.
TRANSPORTS = ("raw", "compressed")


def check_transport(value: str, parameter: str = "image_transport") -> str:
    """The value, or ValueError naming the parameter."""
    if value not in TRANSPORTS:
        raise ValueError(f"parameter '{parameter}': '{value}' is not a transport "
                         f"(choose from {', '.join(TRANSPORTS)})")
    return value


def subscription(node: Any, topic: str, transport: str) -> tuple[Any, str]:
    """(message type, topic) to subscribe for the relative image topic ``topic``."""
    if check_transport(transport) == "raw":
        return Image, topic
    return CompressedImage, node.resolve_topic_name(topic).rstrip("/") + "/compressed"


def to_rgb(msg: Any) -> np.ndarray:
    """(H, W, 3) RGB of an rgb8/bgr8 Image or of a CompressedImage (JPEG / PNG)."""
    if isinstance(msg, CompressedImage):
        return images.decode_rgb(msg.format, memoryview(msg.data))
    return conv.image_to_rgb(msg)


def to_labels(msg: Any) -> np.ndarray:
    """(H, W) class ids of a mono8 Image or a PNG CompressedImage (JPEG refused)."""
    if isinstance(msg, CompressedImage):
        return images.decode_labels(msg.format, memoryview(msg.data))
    return conv.image_to_labels(msg)


def compressed_image(image: Any, codec: str, encoding: str, header: Any,
                     jpeg_quality: int = 95) -> CompressedImage:
    """A CompressedImage as compressed_image_transport publishes it (format and bytes)."""
    fmt, data = images.encode(image, codec, encoding, jpeg_quality=jpeg_quality)
    msg = CompressedImage(header=header, format=fmt)
    msg.data = data
    return msg


__all__ = ["TRANSPORTS", "check_transport", "compressed_image", "subscription", "to_labels",
           "to_rgb"]
