"""A small ONNX graph builder over published weights: layers by state_dict prefix, shapes checked.

The networks are rebuilt from their papers' code (read, not copied) as plain ONNX operators, so
running them needs onnxruntime only. Each layer asks :class:`Weights` for its tensors by the
PyTorch ``state_dict`` name with the shape the architecture implies; a weights file that does not
fit fails there with the tensor's name and both shapes instead of producing a wrong network.

Folding: a BatchNorm directly after a convolution (or transposed convolution) is folded into its
weights and bias, which is exact in inference. A BatchNorm after a sum or concatenation stays a
``BatchNormalization`` node. Spatial sizes are static (the export size), so sizes of resizes and
adaptive poolings are computed here, not in the graph.
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

#: ONNX opset of the exported graphs (Resize with align_corners, AveragePool count_include_pad).
OPSET = 17


class Weights:
    """The arrays of a ``.npz`` state_dict; hands them out by name with their shapes checked.

    ``num_batches_tracked`` entries are training counters and are ignored. :meth:`check_all_used`
    refuses leftovers: an extra tensor means the file is of another architecture or variant.
    """

    def __init__(self, path: str | Path, arch: str) -> None:
        self.path = Path(path)
        self.arch = arch
        if not self.path.is_file():
            raise FileNotFoundError(f"weights file not found: {self.path}")
        try:
            with np.load(self.path, allow_pickle=False) as data:
                self.arrays = {k: np.asarray(data[k]) for k in data.files
                               if not k.endswith("num_batches_tracked")}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise ValueError(f"{self.path}: not a readable .npz weights file ({exc})") from None
        self.used: set[str] = set()

    def take(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """float32 array ``key`` of exactly ``shape``, or a one-line error naming both."""
        if key not in self.arrays:
            raise ValueError(f"{self.path}: no tensor '{key}' (the {self.arch} architecture "
                             f"needs one of shape {tuple(shape)})")
        array = self.arrays[key]
        if tuple(array.shape) != tuple(shape):
            raise ValueError(f"{self.path}: tensor '{key}' has shape {tuple(array.shape)}, the "
                             f"{self.arch} architecture needs {tuple(shape)}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{self.path}: tensor '{key}' has non-finite values")
        self.used.add(key)
        return array.astype(np.float32)

    def check_all_used(self) -> None:
        extra = sorted(set(self.arrays) - self.used)
        if extra:
            raise ValueError(f"{self.path}: tensor '{extra[0]}' (shape "
                             f"{tuple(self.arrays[extra[0]].shape)}) is not part of the "
                             f"{self.arch} architecture ({len(extra)} unused tensors)")

    @property
    def parameters(self) -> int:
        return int(sum(self.arrays[k].size for k in self.used))


@dataclass(frozen=True)
class T:
    """A tensor of the graph being built: its name and (channels, height, width), batch 1."""

    name: str
    c: int
    h: int
    w: int


def adaptive_windows(size_in: int, size_out: int) -> list[tuple[int, int]]:
    """PyTorch's adaptive average pooling windows on one axis: [floor(i n/m), ceil((i+1) n/m))."""
    return [((i * size_in) // size_out, -((-(i + 1) * size_in) // size_out))
            for i in range(size_out)]


def bn_affine(weights: Weights, prefix: str, channels: int, eps: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Scale and shift of an inference BatchNorm: y = x * scale + shift."""
    gamma = weights.take(f"{prefix}.weight", (channels,))
    beta = weights.take(f"{prefix}.bias", (channels,))
    mean = weights.take(f"{prefix}.running_mean", (channels,))
    var = weights.take(f"{prefix}.running_var", (channels,))
    scale = gamma / np.sqrt(var.astype(np.float64) + eps).astype(np.float32)
    return scale.astype(np.float32), (beta - mean * scale).astype(np.float32)


class GraphBuilder:
    """Collects nodes and constants; layer helpers take state_dict prefixes."""

    def __init__(self, weights: Weights, bn_eps: float) -> None:
        self.weights = weights
        self.bn_eps = bn_eps
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.folded = 0
        self._count = 0

    # -- plumbing ------------------------------------------------------------------------------
    def _name(self, hint: str) -> str:
        self._count += 1
        return f"{hint}_{self._count}"

    def const(self, array: np.ndarray, hint: str) -> str:
        name = self._name(hint)
        self.initializers.append(numpy_helper.from_array(np.ascontiguousarray(array), name))
        return name

    def op(self, op_type: str, inputs: list[str], hint: str | None = None, **attrs) -> str:
        out = self._name(hint or op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], **attrs))
        return out

    # -- layers --------------------------------------------------------------------------------
    def conv(self, x: T, key: str, cout: int, k: int, stride: int = 1, dilation: int = 1,
             groups: int = 1, bn: str | None = None, bias: str | None = None,
             prelu: str | None = None, padding: int | None = None) -> T:
        """Conv2d ``key`` (+ folded BatchNorm ``bn``) (+ PReLU ``prelu``), PyTorch padding."""
        w = self.weights.take(key, (cout, x.c // groups, k, k))
        b = self.weights.take(bias, (cout,)) if bias else np.zeros(cout, np.float32)
        if bn:
            scale, shift = bn_affine(self.weights, bn, cout, self.bn_eps)
            w = w * scale[:, None, None, None]
            b = b * scale + shift
            self.folded += 1
        pad = (k - 1) // 2 * dilation if padding is None else padding
        inputs = [x.name, self.const(w, "w")]
        if bn or bias:
            inputs.append(self.const(b.astype(np.float32), "b"))
        y = self.op("Conv", inputs, "conv", kernel_shape=[k, k], strides=[stride, stride],
                    pads=[pad] * 4, dilations=[dilation, dilation], group=groups)
        h = (x.h + 2 * pad - dilation * (k - 1) - 1) // stride + 1
        w_out = (x.w + 2 * pad - dilation * (k - 1) - 1) // stride + 1
        out = T(y, cout, h, w_out)
        return self.prelu(out, prelu) if prelu else out

    def conv_transpose2(self, x: T, key: str, cout: int, bn: str | None = None,
                        prelu: str | None = None) -> T:
        """ConvTranspose2d(kernel 2, stride 2, no padding), BatchNorm folded per output channel."""
        w = self.weights.take(key, (x.c, cout, 2, 2))
        inputs = [x.name]
        if bn:
            scale, shift = bn_affine(self.weights, bn, cout, self.bn_eps)
            w = w * scale[None, :, None, None]
            inputs += [self.const(w, "wt"), self.const(shift, "b")]
            self.folded += 1
        else:
            inputs.append(self.const(w, "wt"))
        y = self.op("ConvTranspose", inputs, "deconv", kernel_shape=[2, 2], strides=[2, 2])
        out = T(y, cout, 2 * x.h, 2 * x.w)
        return self.prelu(out, prelu) if prelu else out

    def batchnorm(self, x: T, prefix: str) -> T:
        """A BatchNorm that follows no convolution (after a sum or a concatenation)."""
        c = x.c
        take = self.weights.take
        inputs = [x.name] + [self.const(take(f"{prefix}.{p}", (c,)), "bn")
                             for p in ("weight", "bias", "running_mean", "running_var")]
        return T(self.op("BatchNormalization", inputs, "bn", epsilon=self.bn_eps), c, x.h, x.w)

    def prelu(self, x: T, key: str) -> T:
        """PReLU with per-channel slopes a, written as elementwise ops onnxruntime runs fast.

        onnxruntime's PRelu broadcasts slowly (3.5x the time of the forms below on a 32 x 256 x
        512 tensor) and is not fused into its blocked-layout convolutions. All a <= 1:
        max(x, a x); all a >= 1: min(x, a x); mixed: x + (a - 1) min(x, 0). All are exact.
        """
        slope = self.weights.take(key, (x.c,)).reshape(x.c, 1, 1)
        if slope.max() <= 1.0 or slope.min() >= 1.0:
            scaled = self.op("Mul", [x.name, self.const(slope, "slope")], "prelu_ax")
            y = self.op("Max" if slope.max() <= 1.0 else "Min", [x.name, scaled], "prelu")
        else:
            neg = self.op("Min", [x.name, self.const(np.zeros(1, np.float32), "zero")], "neg")
            neg = self.op("Mul", [neg, self.const(slope - 1.0, "slope")], "prelu_neg")
            y = self.op("Add", [x.name, neg], "prelu")
        return T(y, x.c, x.h, x.w)

    def add(self, a: T, b: T) -> T:
        if (a.c, a.h, a.w) != (b.c, b.h, b.w):
            raise AssertionError(f"add of {a} and {b}")
        return T(self.op("Add", [a.name, b.name], "add"), a.c, a.h, a.w)

    def concat(self, parts: list[T]) -> T:
        if len({(p.h, p.w) for p in parts}) != 1:
            raise AssertionError(f"concat of {parts}")
        y = self.op("Concat", [p.name for p in parts], "cat", axis=1)
        return T(y, sum(p.c for p in parts), parts[0].h, parts[0].w)

    def avg_pool3s2(self, x: T) -> T:
        """AvgPool2d(3, stride 2, padding 1), zero padding counted (PyTorch's default)."""
        y = self.op("AveragePool", [x.name], "avgpool", kernel_shape=[3, 3], strides=[2, 2],
                    pads=[1, 1, 1, 1], count_include_pad=1)
        return T(y, x.c, (x.h - 1) // 2 + 1, (x.w - 1) // 2 + 1)

    def resize_bilinear(self, x: T, h: int, w: int) -> T:
        """F.interpolate(mode='bilinear', align_corners=True) to (h, w)."""
        sizes = self.const(np.array([1, x.c, h, w], np.int64), "sizes")
        y = self.op("Resize", [x.name, "", "", sizes], "resize", mode="linear",
                    coordinate_transformation_mode="align_corners")
        return T(y, x.c, h, w)

    def adaptive_avg_pool(self, x: T, h: int, w: int) -> T:
        """F.adaptive_avg_pool2d to (h, w), axis by axis (the windows are separable).

        Equal windows along an axis become an AveragePool (plus a Gather when they overlap or
        skip), unequal ones a MatMul with the averaging matrix (only small sizes have those).
        """
        y = self._pool_axis(x, 3, x.w, w)
        y = self._pool_axis(T(y.name, x.c, x.h, w), 2, x.h, h)
        return T(y.name, x.c, h, w)

    def _pool_axis(self, x: T, axis: int, n_in: int, n_out: int) -> T:
        if n_in == n_out:
            return x
        windows = adaptive_windows(n_in, n_out)
        sizes = {e - s for s, e in windows}
        shape = [x.c, x.h, x.w]
        shape[axis - 1] = n_out
        if len(sizes) == 1:
            k = sizes.pop()
            starts = [s for s, _ in windows]
            regular = starts == [i * k for i in range(n_out)]
            kernel = [k, 1] if axis == 2 else [1, k]
            step = k if regular else 1
            stride = [step, 1] if axis == 2 else [1, step]
            y = self.op("AveragePool", [x.name], "apool", kernel_shape=kernel, strides=stride)
            if not regular:
                y = self.op("Gather", [y, self.const(np.array(starts, np.int64), "idx")],
                            "gather", axis=axis)
            return T(y, *shape)
        matrix = np.zeros((n_out, n_in), np.float32)
        for i, (s, e) in enumerate(windows):
            matrix[i, s:e] = 1.0 / (e - s)
        if axis == 3:  # (.., h, n_in) @ (n_in, n_out)
            y = self.op("MatMul", [x.name, self.const(matrix.T.copy(), "pool")], "pool")
        else:  # (n_out, n_in) @ (.., n_in, w)
            y = self.op("MatMul", [self.const(matrix, "pool"), x.name], "pool")
        return T(y, *shape)

    def global_avg_pool(self, x: T) -> T:
        return T(self.op("GlobalAveragePool", [x.name], "gap"), x.c, 1, 1)

    def sigmoid(self, x: T) -> T:
        return T(self.op("Sigmoid", [x.name], "sigmoid"), x.c, x.h, x.w)

    def mul(self, a: T, b: T) -> T:
        return T(self.op("Mul", [a.name, b.name], "mul"), a.c, max(a.h, b.h), max(a.w, b.w))

    def channel_shuffle(self, x: T, groups: int) -> T:
        """View (groups, C/groups) -> transpose -> flatten: channel j*groups + i <- i*C/g + j."""
        per = x.c // groups
        perm = np.array([i * per + j for j in range(per) for i in range(groups)], np.int64)
        return T(self.op("Gather", [x.name, self.const(perm, "shuffle")], "shuffle", axis=1),
                 x.c, x.h, x.w)

    # -- output --------------------------------------------------------------------------------
    def model(self, x: T, out: T, graph_name: str, doc: str) -> onnx.ModelProto:
        """The finished model: input ``input`` (1 x 3 x H x W float), output ``logits``."""
        self.nodes.append(helper.make_node("Identity", [out.name], ["logits"]))
        graph = helper.make_graph(
            self.nodes, graph_name,
            [helper.make_tensor_value_info(x.name, TensorProto.FLOAT, [1, 3, x.h, x.w])],
            [helper.make_tensor_value_info("logits", TensorProto.FLOAT,
                                           [1, out.c, out.h, out.w])],
            self.initializers)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                                  producer_name="semcal_ros", doc_string=doc)
        model.ir_version = 8
        helper.set_model_props(model, {"folded_batchnorms": str(self.folded)})
        onnx.checker.check_model(model, full_check=True)
        return model


def ceil_scale(size: int, scale: float) -> int:
    """``int(math.ceil(size * scale))`` exactly as the reference code computes pyramid sizes."""
    return int(math.ceil(size * scale))
