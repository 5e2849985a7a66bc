"""The per-camera input cache (semcal_ros.ros.camera_inputs), without DDS: messages are built and
handed to it directly, as a subscription would."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")

from semcal_ros.engine.camera import CameraModel  # noqa: E402
from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros.camera_inputs import (CameraInputs, CameraTopics,  # noqa: E402
                                          camera_topics)


def _camera(frame: str = "north_optical") -> CameraModel:
    return CameraModel(64, 48, np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]), np.zeros(5),
                       frame_id=frame)


def _labels(frame: str = "north_optical", shape=(48, 64)):
    return conv.numpy_to_image(np.full(shape, 11, np.uint8), "mono8", conv.make_header(frame, 1.0))


def test_topics_of_named_and_unnamed_cameras():
    assert camera_topics([]) == [CameraTopics("", "camera/labels", "camera/camera_info",
                                              "camera/image_raw")]
    north, south = camera_topics(["north", "south"])
    assert (north.labels, north.camera_info, north.image) == ("north/labels", "north/camera_info",
                                                              "north/image_raw")
    assert south.name == "south" and south.label == "camera 'south'"
    with pytest.raises(ValueError, match="'north' given more than once|north given more"):
        camera_topics(["north", "north"])
    with pytest.raises(ValueError, match="'no/slash' cannot name a camera"):
        camera_topics(["no/slash"])


def test_keeps_the_newest_good_messages_and_names_each_refusal_once():
    logged: list[str] = []
    cam = CameraInputs(CameraTopics.for_name("north"), logged.append, lambda t: "/" + t)
    assert cam.problems() == ["no label image received yet (topic '/north/labels')",
                              "no CameraInfo received yet (topic '/north/camera_info')"]
    assert cam.on_labels(_labels()) and cam.on_camera_info(conv.model_to_camera_info(
        _camera(), conv.make_header("north_optical", 1.0)))
    assert cam.problems() == [] and cam.snapshot().frame_id == "north_optical"
    assert cam.values()["label_image"] == "64x48"

    bad_info = conv.model_to_camera_info(_camera(), conv.make_header("north_optical", 2.0))
    k = np.array(bad_info.k, float)
    k[0] = float("nan")
    bad_info.k = k
    rgb = conv.numpy_to_image(np.zeros((48, 64, 3), np.uint8), "rgb8",
                              conv.make_header("north_optical", 2.0))
    for _ in range(3):  # the same refusal again: logged once
        assert not cam.on_camera_info(bad_info)
        assert not cam.on_labels(rgb)
    assert logged == ["ignoring CameraInfo (north): K contains NaN or infinite values",
                      "ignoring label image (north): expected a mono8 label image, got encoding "
                      "'rgb8'"], logged
    assert set(cam.refusals()) == {"CameraInfo", "label image"}
    # what was held is kept, and still fits together
    snap = cam.snapshot()
    assert snap.camera is not None and snap.camera.k[0, 0] == 50.0 and snap.labels.shape == (48, 64)
    assert cam.values()["input_error.CameraInfo"] == "K contains NaN or infinite values"
    # a good message clears its refusal; a label image of another size is refused on arrival
    assert cam.on_labels(_labels())
    assert "label image" not in cam.refusals()
    assert not cam.on_labels(_labels(shape=(40, 64)))
    assert cam.refusals()["label image"] == ("the label image is 64x40 but CameraInfo says "
                                             "64x48; keeping the one held")
    assert cam.problems() == [] and cam.snapshot().labels.shape == (48, 64)
    assert cam.on_image(rgb) and cam.snapshot().rgb.shape == (48, 64, 3)


def test_a_goal_names_its_camera_by_name_or_frame():
    cam = CameraInputs(CameraTopics.for_name("north"))
    assert cam.answers_to("north") and not cam.answers_to("north_optical")
    cam.on_labels(_labels())
    assert cam.answers_to("north_optical") and not cam.answers_to("south") \
        and not cam.answers_to("")
    unnamed = CameraInputs(CameraTopics.for_name(""))
    unnamed.on_camera_info(conv.model_to_camera_info(_camera("camera_optical")))
    assert unnamed.answers_to("camera_optical") and not unnamed.answers_to("")
    assert unnamed.problems("other") == [
        "no label image received yet (topic 'camera/labels')",
        "goal asks for camera 'other' but the CameraInfo is from 'camera_optical'"]
