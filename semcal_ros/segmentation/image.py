"""Camera image -> Cityscapes trainId label image, through the user's ONNX model.

The label image is what the calibrator compares with the rendered map, so it has the camera
image's size: the model's output (often smaller, e.g. a quarter of the input for SegFormer) is
turned into labels and resized back with nearest neighbour, which never invents a class between
two others.

Accepted images (decided for the ROS topics this feeds): 8-bit colour in the ROS encodings
``rgb8``, ``bgr8``, ``rgba8`` and ``bgra8`` (alpha is dropped; many camera drivers publish bgra8).
Grey, Bayer and 16-bit images are refused with a message: the model was trained on 8-bit colour,
and guessing a conversion (debayering, a bit shift) would silently change its input.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from semcal_ros.readers import imread
from semcal_ros.engine.labels import INVALID, colorize
from semcal_ros.segmentation.decode import labels_from_class_map, labels_from_logits
from semcal_ros.segmentation.model_config import ImageModelConfig, load_model_config
from semcal_ros.segmentation.onnx_runner import OnnxRunner, RunnerParams
from semcal_ros.segmentation.probabilities import probabilities_from_logits

#: encoding -> (channels, colour order of the first three channels)
ENCODINGS: dict[str, tuple[int, str]] = {
    "rgb8": (3, "RGB"), "bgr8": (3, "BGR"), "rgba8": (4, "RGB"), "bgra8": (4, "BGR"),
}


class ImageSegmenter:
    """Runs an image model; :meth:`segment` is the one call the nodes and the CLI make.

    :meth:`preprocess`, :meth:`infer` and :meth:`postprocess` are its three steps, public so a
    benchmark can time the runner's own work apart from the model's.
    """

    def __init__(self, runner: OnnxRunner, config: ImageModelConfig) -> None:
        self.runner = runner
        self.config = config
        self.lut = config.class_lut()
        w, h = config.input_width, config.input_height
        runner.check_input([1, 3, h, w], f"1 x 3 x input_height x input_width, {config.layout}")
        runner.check_segmentation_output(config.output, config.num_classes)
        # one set of blob parameters per colour order of the incoming image (built once, never
        # mutated, so concurrent callers do not race): (pixel - mean / scale) * scale / std
        self._blobs = {order: _blob_params(config, swap=order != config.channel_order)
                       for order in ("RGB", "BGR")}

    @classmethod
    def from_files(cls, model: str | Path, config: str | Path,
                   params: RunnerParams = RunnerParams()) -> "ImageSegmenter":
        cfg = load_model_config(config, ImageModelConfig)
        return cls(OnnxRunner(model, params, cfg.input_name, cfg.output_name), cfg)

    def segment(self, image: np.ndarray, encoding: str = "rgb8") -> np.ndarray:
        """(H, W) uint8 Cityscapes trainIds (255 = ignored) of an 8-bit colour image."""
        image = np.asarray(image)
        tensor = self.preprocess(image, encoding)
        return self.postprocess(self.infer(tensor), image.shape[:2])

    def segment_with_probabilities(self, image: np.ndarray, encoding: str = "rgb8"
                                   ) -> tuple[np.ndarray, np.ndarray]:
        """The labels of :meth:`segment` and, pixel-aligned with them, (H, W, 19) float32
        trainId probabilities (:mod:`semcal_ros.segmentation.probabilities`)."""
        if self.config.output != "logits":
            raise ValueError(f"{self.runner.path}: the model outputs a class map; class "
                             "probabilities need a model with output: logits")
        image = np.asarray(image)
        logits = self.infer(self.preprocess(image, encoding))
        labels = self.postprocess(logits, image.shape[:2])
        return labels, probabilities_from_logits(logits, self.lut, image.shape[:2])

    def preprocess(self, image: np.ndarray, encoding: str = "rgb8") -> np.ndarray:
        """Checked image -> (1, 3, input_height, input_width) float32 network input."""
        order = check_image(image, encoding)
        image = np.asarray(image)
        if image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_RGBA2RGB)  # drops alpha, keeps the order
        size = (self.config.input_width, self.config.input_height)
        if image.shape[1::-1] != size:
            image = cv2.resize(image, size, interpolation=cv2.INTER_LINEAR)
        return cv2.dnn.blobFromImageWithParams(np.ascontiguousarray(image), self._blobs[order])

    def infer(self, tensor: np.ndarray) -> np.ndarray:
        output = self.runner.run(tensor)
        self.runner.check_segmentation_output(self.config.output, self.config.num_classes,
                                              shape=output.shape)
        return output

    def postprocess(self, output: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """Model output -> trainIds at ``size`` = (height, width) of the camera image."""
        if self.config.output == "logits":
            labels = labels_from_logits(output, self.lut)
        else:
            labels = labels_from_class_map(output, self.lut, INVALID)
        if labels.shape != tuple(size):
            labels = cv2.resize(labels, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)
        return labels


def _blob_params(config: ImageModelConfig, swap: bool) -> "cv2.dnn.Image2BlobParams":
    """OpenCV's one-pass NCHW conversion; mean and factor are given in the model's order."""
    params = cv2.dnn.Image2BlobParams()
    params.scalefactor = tuple(config.scale / s for s in config.std) + (0.0,)
    params.mean = tuple(m / config.scale for m in config.mean) + (0.0,)
    params.size = (config.input_width, config.input_height)
    params.ddepth = cv2.CV_32F
    params.swapRB = swap
    return params


def check_image(image: np.ndarray, encoding: str) -> str:
    """Raise a clear ValueError unless ``image`` is an 8-bit colour image in ``encoding``.

    Returns the colour order ("RGB" or "BGR") of its first three channels.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"unsupported image encoding '{encoding}': the image segmenter takes "
                         f"8-bit colour ({', '.join(ENCODINGS)})")
    channels, order = ENCODINGS[encoding]
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"image has dtype {image.dtype}; only 8-bit images ({encoding}) are "
                         "supported - convert 16-bit or float images to 8 bit first")
    got = 1 if image.ndim == 2 else (image.shape[2] if image.ndim == 3 else None)
    if got != channels or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"image of shape {image.shape} does not match encoding '{encoding}' "
                         f"(expected H x W x {channels}, non-empty)")
    return order


def read_colour_image(path: str | Path) -> tuple[np.ndarray, str]:
    """An image file as it is stored, with its encoding ("bgr8" or "bgra8"): OpenCV's order.

    Refuses what the segmenter refuses, naming the file: 16-bit, grey or 2-channel images.
    """
    path = Path(path)
    image = imread(path, cv2.IMREAD_UNCHANGED)
    if image.dtype != np.uint8:
        raise ValueError(f"{path}: {8 * image.dtype.itemsize}-bit image ({image.dtype}); only "
                         "8-bit colour images are supported")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels not in (3, 4):
        raise ValueError(f"{path}: {channels}-channel image; the image segmenter needs 8-bit "
                         "colour (3 channels, or 4 with alpha)")
    return image, ("bgr8" if channels == 3 else "bgra8")


def label_overlay(rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """The image with label colours blended in; ignored pixels (255) show the image only."""
    blended = cv2.addWeighted(colorize(labels), alpha, np.ascontiguousarray(rgb), 1.0 - alpha, 0)
    return np.where((labels == INVALID)[:, :, None], rgb, blended)
