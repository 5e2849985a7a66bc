"""Small real ONNX models for the segmentation tests and benchmark.

No pretrained network can be downloaded here, so the tests build their own with the ``onnx``
package: a 1x1 convolution is a per-pixel linear classifier, and with the weights of a
nearest-centre rule (score_k = 2 c_k . x - |c_k|^2, the negative squared distance up to a term
common to all classes) it labels each pixel by the nearest of K known centres - colours for an
image model, ranges or heights for a range-image model. Their outputs are therefore known exactly,
while onnxruntime runs them like any exported network.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


def conv1x1_model(path: str | Path, weights: np.ndarray, bias: np.ndarray,
                  input_shape: Sequence[int | str], *, input_name: str = "input",
                  output_name: str = "output", stride: int = 1, argmax: bool = False,
                  class_map_channel: bool = False) -> Path:
    """Write a model: Conv(1x1, ``stride``) with ``weights`` (C_out, C_in) and ``bias`` (C_out,).

    ``argmax`` appends ArgMax over the channels, making a class-map output (N x H x W int64, or
    N x 1 x H x W with ``class_map_channel``). String entries in ``input_shape`` are symbolic.
    """
    weights = np.asarray(weights, dtype=np.float32)
    c_out, c_in = weights.shape
    w = numpy_helper.from_array(weights.reshape(c_out, c_in, 1, 1), "W")
    b = numpy_helper.from_array(np.asarray(bias, dtype=np.float32), "B")
    conv_out = "scores" if argmax else output_name
    nodes = [helper.make_node("Conv", [input_name, "W", "B"], [conv_out],
                              kernel_shape=[1, 1], strides=[stride, stride])]
    if argmax:
        nodes.append(helper.make_node("ArgMax", ["scores"], [output_name], axis=1,
                                      keepdims=int(class_map_channel)))
        out = helper.make_tensor_value_info(output_name, TensorProto.INT64, None)
    else:
        out = helper.make_tensor_value_info(output_name, TensorProto.FLOAT, None)
    inp = helper.make_tensor_value_info(input_name, TensorProto.FLOAT, list(input_shape))
    graph = helper.make_graph(nodes, "semcal_test_model", [inp], [out], initializer=[w, b])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    model = onnx.shape_inference.infer_shapes(model)
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path


def nearest_centre_weights(centres: np.ndarray, active: Sequence[bool] | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Weights and bias of a 1x1 conv that scores each class by -|x - c_k|^2 (+ const).

    ``centres`` (K, C_in) are in the network's (normalised) input space; channels where
    ``active`` is False do not count.
    """
    centres = np.asarray(centres, dtype=np.float64)
    mask = np.ones(centres.shape[1], bool) if active is None else np.asarray(active, bool)
    c = centres * mask
    return (2.0 * c).astype(np.float32), (-(c ** 2).sum(axis=1)).astype(np.float32)


def colour_model(path: str | Path, palette_rgb: np.ndarray, width: int, height: int, *,
                 channel_order: str = "RGB", scale: float = 1.0,
                 mean: Sequence[float] = (0, 0, 0), std: Sequence[float] = (1, 1, 1),
                 **kwargs) -> Path:
    """An image model labelling each pixel by the nearest colour of ``palette_rgb`` (K, 3)."""
    colours = np.asarray(palette_rgb, dtype=np.float64)
    if channel_order == "BGR":
        colours = colours[:, ::-1]
    normalised = (colours * scale - np.asarray(mean)) / np.asarray(std)
    weights, bias = nearest_centre_weights(normalised)
    return conv1x1_model(path, weights, bias, [1, 3, height, width], **kwargs)


def range_channel_model(path: str | Path, channel: int, centres: Sequence[float],
                        mean: float, std: float, height: int, width: int, **kwargs) -> Path:
    """A range-image model labelling each pixel by the nearest of ``centres`` on one channel
    (0 range, 1 x, 2 y, 3 z, 4 remission), given that channel's normalisation."""
    normalised = np.zeros((len(centres), 5))
    normalised[:, channel] = (np.asarray(centres, dtype=np.float64) - mean) / std
    active = np.zeros(5, bool)
    active[channel] = True
    weights, bias = nearest_centre_weights(normalised, active)
    return conv1x1_model(path, weights, bias, [1, 5, height, width], **kwargs)
