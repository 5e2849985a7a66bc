"""The messages a segmenter would publish for one camera of a ``semcal scene --cameras N`` folder.

The multi-camera test, its benchmark and the drift demo all feed a calibrator or monitor from the
files of ``cameras.yaml``'s entries; this is the one place that turns an entry into messages.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from semcal_ros.io.files import read_camera_info, read_label_image, read_rgb_image
from semcal_ros.ros import conversions as conv


def camera_messages(scene: Path, entry: dict, stamp: float | None = None) -> dict[str, Any]:
    """``{topic: message}`` for the entry's label image (mono8), camera image (rgb8) and
    CameraInfo, stamped ``stamp`` (None: now). camera_info.yaml (the ROS calibration format) has
    no frame id: the entry's ``frame_id`` is used, as in the scene's bag."""
    folder = Path(scene) / entry["folder"]
    camera = replace(read_camera_info(folder / "camera_info.yaml"), frame_id=entry["frame_id"])
    header = conv.make_header(camera.frame_id, stamp)
    topics = entry["topics"]
    return {topics["labels"]: conv.numpy_to_image(read_label_image(folder / "labels.png"),
                                                  "mono8", header),
            topics["image_raw"]: conv.numpy_to_image(read_rgb_image(folder / "image.png"),
                                                     "rgb8", header),
            topics["camera_info"]: conv.model_to_camera_info(camera, header)}
