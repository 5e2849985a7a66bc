"""DeepLab v3 with a MobileNet-EdgeTPU (x0.75) backbone, Cityscapes, as an ONNX graph.

The published model is an int8 TFLite file (google-coral/test_data). Its weights come dequantised
to float32 in a ``.npz`` (keys ``<layer>/weights``, ``<layer>/bias``: BatchNorms already folded
in) and its 84 operators, in order, in a ``.graph.json`` beside it (inputs and outputs by tensor
index, strides, dilations, padding, fused activation; ``tensors[i].npz_key`` names the npz entry
of a constant). This module reads that operator list and writes each operator as ONNX, in NCHW:

* ``CONV_2D`` (weights ``[out, kh, kw, in]``) and ``DEPTHWISE_CONV_2D`` (``[1, kh, kw, C]``) ->
  ``Conv`` (``group = C`` for depthwise), TF "SAME" padding computed for the export size
  (the extra pixel goes after, as in TensorFlow), fused ReLU -> ``Relu``;
* ``ADD`` -> ``Add``; ``CONCATENATION`` on NHWC axis 3 -> ``Concat`` on axis 1;
* the head's image pooling: ``AVERAGE_POOL_2D`` with a window the size of its input (33 x 33 at
  the file's 513 x 513) is a global average -> ``GlobalAveragePool``, and ``TILE`` back to the
  feature size -> ``Expand``, so the graph is the same network at any input size;
* ``QUANTIZE`` (int8 bookkeeping) -> nothing; a ``RESIZE_BILINEAR`` to the size its input already
  has -> nothing; the last one (align_corners, to the file's input size) -> ``Resize`` to the
  export's input size;
* ``ARG_MAX`` -> nothing: the graph outputs the 19 logits (Cityscapes trainIds 0-18) at the input
  size, and the runner takes the argmax (and the softmax, for class probabilities).

Input: RGB, ``(x - 128) / 128`` (the model config says so; the graph itself starts with the first
convolution). Any operator or attribute outside this list is refused with its index, so a file of
another architecture fails clearly instead of building a wrong network.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import onnx

from semcal_ros.segmentation.export.graph import GraphBuilder, T, Weights

NUM_CLASSES = 19
#: Operators this builder writes (anything else in the graph file is refused).
SUPPORTED = {"CONV_2D", "DEPTHWISE_CONV_2D", "ADD", "AVERAGE_POOL_2D", "TILE", "QUANTIZE",
             "CONCATENATION", "RESIZE_BILINEAR", "ARG_MAX"}


def graph_path_for(weights_path: str | Path) -> Path:
    """The operator list published beside the weights: ``X.npz`` -> ``X.graph.json``."""
    path = Path(weights_path)
    return path.with_name(path.stem + ".graph.json")


def read_graph(path: str | Path) -> dict[str, Any]:
    """The ``.graph.json`` operator list; a missing or malformed file is one clear line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"graph file not found: {path} (the EdgeTPU DeepLab export "
                                "needs the .graph.json published beside the .npz)")
    try:
        graph = json.loads(path.read_text())
        inputs, outputs = graph["inputs"], graph["outputs"]
        if not isinstance(graph["ops"], list) or not isinstance(graph["tensors"], list):
            raise TypeError("'ops' and 'tensors' must be lists")
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not an operator list (.graph.json with inputs, outputs, ops, "
                         f"tensors): {exc}") from None
    if len(inputs) != 1 or len(outputs) != 1:
        raise ValueError(f"{path}: expected one input and one output, got {len(inputs)} and "
                         f"{len(outputs)}")
    return graph


def same_pads(size: int, k: int, stride: int, dilation: int) -> tuple[int, int, int]:
    """TF "SAME": output ceil(size / stride); (pad before, pad after, output size)."""
    out = -(-size // stride)
    total = max((out - 1) * stride + (k - 1) * dilation + 1 - size, 0)
    return total // 2, total - total // 2, out


class _Builder:
    """Walks the operator list once, keeping each TFLite tensor's ONNX tensor (NCHW)."""

    def __init__(self, graph: dict[str, Any], weights: Weights, path: Path,
                 width: int, height: int) -> None:
        self.g = GraphBuilder(weights, bn_eps=0.0)
        self.weights = weights
        self.path = path
        self.tensors = graph["tensors"]
        self.values: dict[int, T] = {}
        self.width, self.height = width, height
        (self.input_index,) = graph["inputs"]
        shape = self.tensors[self.input_index]["shape"]  # NHWC of the file's build (513 x 513)
        if len(shape) != 4 or shape[3] != 3:
            raise ValueError(f"{path}: input tensor has shape {shape}, expected [1, H, W, 3]")
        self.file_size = (shape[1], shape[2])
        self.values[self.input_index] = T("input", 3, height, width)

    # -- helpers -------------------------------------------------------------------------------
    def const(self, index: int, op: int) -> np.ndarray:
        tensor = self.tensors[index]
        if not tensor.get("const") or "npz_key" not in tensor:
            raise ValueError(f"{self.path}: operator {op} expects a constant at tensor {index}")
        return self.weights.take(tensor["npz_key"], tuple(tensor["shape"]))

    def int_const(self, index: int, op: int) -> list[int]:
        """A small integer constant (a size, tile multiples), read as it is stored."""
        tensor = self.tensors[index]
        key = tensor.get("npz_key")
        if not tensor.get("const") or key not in self.weights.arrays:
            raise ValueError(f"{self.path}: operator {op} expects a constant at tensor {index}")
        self.weights.used.add(key)
        return [int(v) for v in np.asarray(self.weights.arrays[key]).ravel()]

    def file_shape(self, index: int) -> tuple[int, int]:
        """(H, W) the tensor has in the file's own build (for the pooling and resize rules)."""
        shape = self.tensors[index]["shape"]
        return int(shape[1]), int(shape[2])

    def act(self, x: T, code: int, op: int) -> T:
        if code == 0:
            return x
        if code == 1:
            return T(self.g.op("Relu", [x.name], "relu"), x.c, x.h, x.w)
        raise ValueError(f"{self.path}: operator {op}: fused activation {code} is not supported "
                         "(0 = none, 1 = ReLU)")

    # -- operators -----------------------------------------------------------------------------
    def conv(self, op: dict, i: int, depthwise: bool) -> T:
        x = self.values[op["inputs"][0]]
        w = self.const(op["inputs"][1], i)
        if depthwise:
            if w.shape[0] != 1 or w.shape[3] != x.c:
                raise ValueError(f"{self.path}: operator {i}: depthwise weights {w.shape} do not "
                                 f"fit {x.c} channels (depth multiplier 1 expected)")
            w = np.transpose(w, (3, 0, 1, 2))  # [C, 1, kh, kw]
            groups = x.c
        else:
            if w.shape[3] != x.c:
                raise ValueError(f"{self.path}: operator {i}: weights {w.shape} take {w.shape[3]} "
                                 f"channels, the input has {x.c}")
            w = np.transpose(w, (0, 3, 1, 2))  # [out, in, kh, kw]
            groups = 1
        cout, kh, kw = w.shape[0], w.shape[2], w.shape[3]
        b = self.const(op["inputs"][2], i)
        if b.shape != (cout,):
            raise ValueError(f"{self.path}: operator {i}: bias {b.shape} for {cout} outputs")
        sh, sw = op["stride"]
        dh, dw = op.get("dilation", [1, 1])
        if op.get("padding") == "SAME":
            top, bottom, h = same_pads(x.h, kh, sh, dh)
            left, right, w_out = same_pads(x.w, kw, sw, dw)
        elif op.get("padding") == "VALID":
            top = bottom = left = right = 0
            h = (x.h - (kh - 1) * dh - 1) // sh + 1
            w_out = (x.w - (kw - 1) * dw - 1) // sw + 1
        else:
            raise ValueError(f"{self.path}: operator {i}: padding {op.get('padding')!r}")
        y = self.g.op("Conv", [x.name, self.g.const(np.ascontiguousarray(w), "w"),
                               self.g.const(b, "b")], "conv",
                      kernel_shape=[kh, kw], strides=[sh, sw], dilations=[dh, dw],
                      pads=[top, left, bottom, right], group=groups)
        return self.act(T(y, cout, h, w_out), op.get("act", 0), i)

    def average_pool(self, op: dict, i: int) -> T:
        x = self.values[op["inputs"][0]]
        if (list(op.get("filter", [])) != list(self.file_shape(op["inputs"][0]))
                or op.get("padding") != "VALID"):
            raise ValueError(f"{self.path}: operator {i}: only an average pool over the whole "
                             "feature map (DeepLab's image pooling) is supported")
        return T(self.g.op("GlobalAveragePool", [x.name], "image_pool"), x.c, 1, 1)

    def tile(self, op: dict, i: int) -> T:
        x = self.values[op["inputs"][0]]
        multiples = self.int_const(op["inputs"][1], i)
        target = self.file_shape(op["outputs"][0])
        if x.h != 1 or x.w != 1 or multiples != [1, *target, 1]:
            raise ValueError(f"{self.path}: operator {i}: only tiling a pooled 1 x 1 map back "
                             "to the feature size is supported")
        # the feature map it is concatenated with: the pooled branch's input
        h, w = self._feature.h, self._feature.w
        shape = self.g.const(np.array([1, x.c, h, w], np.int64), "shape")
        return T(self.g.op("Expand", [x.name, shape], "tile"), x.c, h, w)

    def resize(self, op: dict, i: int) -> T | None:
        x = self.values[op["inputs"][0]]
        size = self.int_const(op["inputs"][1], i)
        if not op.get("align_corners") or op.get("half_pixel_centers"):
            raise ValueError(f"{self.path}: operator {i}: only align_corners resizes are "
                             "supported")
        if tuple(size) == self.file_shape(op["inputs"][0]):
            return x  # to the size it already has
        if tuple(size) != self.file_size:
            raise ValueError(f"{self.path}: operator {i}: resize to {size}, neither the input "
                             f"size {list(self.file_size)} nor its own")
        return self.g.resize_bilinear(x, self.height, self.width)

    def run(self, ops: list[dict]) -> T:
        for i, op in enumerate(ops):
            kind = op.get("op")
            if kind not in SUPPORTED:
                raise ValueError(f"{self.path}: operator {i} is {kind}, which this exporter does "
                                 f"not know ({', '.join(sorted(SUPPORTED))})")
            args = op["inputs"]
            if kind in ("CONV_2D", "DEPTHWISE_CONV_2D"):
                y = self.conv(op, i, kind == "DEPTHWISE_CONV_2D")
            elif kind == "ADD":
                y = self.act(self.g.add(self.values[args[0]], self.values[args[1]]),
                             op.get("act", 0), i)
            elif kind == "AVERAGE_POOL_2D":
                self._feature = self.values[args[0]]
                y = self.average_pool(op, i)
            elif kind == "TILE":
                y = self.tile(op, i)
            elif kind == "QUANTIZE":
                y = self.values[args[0]]
            elif kind == "CONCATENATION":
                if op.get("axis") != 3:
                    raise ValueError(f"{self.path}: operator {i}: concatenation on axis "
                                     f"{op.get('axis')} (only channels, 3, is supported)")
                y = self.g.concat([self.values[a] for a in args])
            elif kind == "RESIZE_BILINEAR":
                y = self.resize(op, i)
            else:  # ARG_MAX: the runner takes it from the logits
                if i != len(ops) - 1:
                    raise ValueError(f"{self.path}: operator {i}: ARG_MAX before the end")
                return self.values[args[0]]
            (out,) = op["outputs"]
            self.values[out] = y
        raise ValueError(f"{self.path}: the operator list does not end in ARG_MAX")


def build(weights: Weights, width: int, height: int,
          graph_path: str | Path | None = None) -> onnx.ModelProto:
    """The network for ``width`` x ``height`` RGB input; logits (1, 19, height, width)."""
    if width < 32 or height < 32:
        raise ValueError(f"input size {width}x{height} is too small (at least 32x32)")
    path = Path(graph_path) if graph_path is not None else graph_path_for(weights.path)
    graph = read_graph(path)
    builder = _Builder(graph, weights, path, width, height)
    logits = builder.run(graph["ops"])
    if (logits.c, logits.h, logits.w) != (NUM_CLASSES, height, width):
        raise ValueError(f"{path}: the graph ends in {logits.c} x {logits.h} x {logits.w}, "
                         f"expected {NUM_CLASSES} x {height} x {width}")
    argmax_axis = graph["ops"][-1]["inputs"][1]  # the dropped ARG_MAX's axis constant
    builder.int_const(argmax_axis, len(graph["ops"]) - 1)
    weights.check_all_used()
    return builder.g.model(T("input", 3, height, width), logits, "edgetpu_deeplab_cityscapes",
                           "DeepLab v3 MobileNet-EdgeTPU (x0.75) Cityscapes, output stride 16, "
                           "from google-coral/test_data's int8 tflite, weights dequantised")
