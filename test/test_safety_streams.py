"""Stream inputs (issue 34, no DDS here; the node is tested as a process in
test_safety_nodes.py): a JPEG that libjpeg decodes only with "Corrupt JPEG data" is refused as
undecodable (OpenCV used it without a word), good JPEGs decode to OpenCV's very pixels, the WARN
about a damaged stream is throttled, and a label or camera image whose size differs from the held
CameraInfo is refused on arrival with the held one kept."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semcal_ros.io import images
from semcal_ros.io.images import UndecodableImage

from jpeg_damage import corrupt_jpeg, opencv_decode_with_stderr


def picture(h: int = 120, w: int = 160) -> np.ndarray:
    rng = np.random.default_rng(0)
    return cv2.GaussianBlur((rng.random((h, w, 3)) * 255).astype(np.uint8), (9, 9), 3)


def test_a_jpeg_libjpeg_warns_about_is_refused():
    fmt, data = images.encode(picture(), "jpeg", "rgb8")
    bad = corrupt_jpeg(data)
    img, said = opencv_decode_with_stderr(bad)
    assert img is not None and "Corrupt JPEG data" in said  # what OpenCV alone let through
    with pytest.raises(UndecodableImage) as info:
        images.decode_rgb(fmt, bad)
    message = str(info.value)
    assert message.startswith(f"{len(bad)} bytes of corrupt JPEG (Corrupt JPEG data: "), message
    assert "\n" not in message


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_good_jpegs_decode_to_opencvs_pixels(encoding):
    rgb = picture(600, 960)
    given = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1].copy(), "mono8": rgb[:, :, 0].copy()}[encoding]
    fmt, data = images.encode(given, "jpeg", encoding)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(images.decode_rgb(fmt, data), bgr[:, :, ::-1])


def test_a_truncated_jpeg_keeps_its_words():
    fmt, data = images.encode(picture(), "jpeg", "rgb8")
    with pytest.raises(UndecodableImage, match=r"^\d+ bytes do not decode as JPEG$"):
        images.decode_rgb(fmt, data[: len(data) // 3])


# --- the camera inputs of the calibrator and the monitor ---------------------------------------
rclpy = pytest.importorskip("rclpy")

from semcal_ros.engine.camera import CameraModel  # noqa: E402
from semcal_ros.ros import conversions as conv  # noqa: E402
from semcal_ros.ros.compressed import compressed_image  # noqa: E402


def _inputs(warnings: list[str], errors: list[str]):
    from semcal_ros.ros.camera_inputs import IMAGE, CameraInputs, CameraTopics

    inputs = CameraInputs(CameraTopics.for_name(""), errors.append, lambda t: "/" + t.lstrip("/"),
                          image_transport="compressed", log_warning=warnings.append)
    inputs._topic[IMAGE] = "/camera/image_raw/compressed"  # as subscribe() sets it
    camera = CameraModel(160, 120, np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]]),
                         np.zeros(5))
    assert inputs.on_camera_info(conv.model_to_camera_info(camera))
    return inputs


def test_corrupt_jpegs_are_dropped_with_a_throttled_warn_naming_the_topic():
    from semcal_ros.ros import camera_inputs
    from semcal_ros.ros.camera_inputs import IMAGE

    warnings: list[str] = []
    inputs = _inputs(warnings, [])
    now = [100.0]
    inputs._clock = lambda: now[0]
    header = conv.make_header("camera_optical", 1.0)
    good = compressed_image(picture(), "jpeg", "rgb8", header)
    assert inputs.on_image(good)
    bad = compressed_image(picture(), "jpeg", "rgb8", header)
    damaged = [corrupt_jpeg(bytes(good.data), seed) for seed in (1, 2, 3)]
    for data in damaged:  # three damaged frames in a row, each with its own reason
        bad.data = data
        assert not inputs.on_image(bad)
        now[0] += 0.1
    assert len(warnings) == 1, warnings
    assert warnings[0].startswith("dropping a camera image on /camera/image_raw/compressed: "
                                  f"{len(damaged[0])} bytes of corrupt JPEG (Corrupt JPEG data")
    now[0] += camera_inputs.WARN_PERIOD
    assert not inputs.on_image(bad)
    assert len(warnings) == 2 and warnings[1].endswith(
        "(2 more dropped since the last warning)"), warnings
    np.testing.assert_array_equal(inputs.snapshot().rgb, images.decode_rgb(good.format,
                                                                            bytes(good.data)))
    assert IMAGE in inputs.refusals()


def test_images_of_another_size_than_the_camera_info_are_refused_on_arrival():
    errors: list[str] = []
    inputs = _inputs([], errors)
    header = conv.make_header("camera_optical", 1.0)
    labels = conv.numpy_to_image(np.full((120, 160), 7, np.uint8), "mono8", header)
    assert inputs.on_labels(labels)
    assert inputs.on_image(compressed_image(picture(), "png", "rgb8", header))
    assert not inputs.on_labels(conv.numpy_to_image(np.full((60, 80), 0, np.uint8), "mono8",
                                                    header))
    assert not inputs.on_image(compressed_image(picture(60, 80), "jpeg", "rgb8", header))
    assert errors == [
        "ignoring label image: the label image is 80x60 but CameraInfo says 160x120; keeping "
        "the one held",
        "ignoring camera image: the camera image is 80x60 but CameraInfo says 160x120; keeping "
        "the one held"], errors
    snap = inputs.snapshot()
    assert snap.labels.shape == (120, 160) and int(snap.labels[0, 0]) == 7
    assert snap.rgb.shape == (120, 160, 3)
    assert inputs.problems() == []  # what is held still fits together
