"""One onnxruntime session on the CPU, with its input and output checked against a config.

A model whose tensors do not fit its config would otherwise fail deep inside onnxruntime with a
message about a node the user never wrote, or worse run and produce labels from misread channels.
The checks here compare the model's declared shapes with what the config promises (symbolic or
unknown dimensions match anything) and name the file, the tensor and both shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, Union

import numpy as np
import onnxruntime as ort

Dim = Union[int, str, None]  # onnxruntime: int, a symbolic name, or unknown


@dataclass(frozen=True)
class RunnerParams:
    """Thread settings. ``threads`` 0 lets onnxruntime pick (one per core); a node sharing the
    machine with the calibrator can give it fewer."""

    threads: int = 0
    inter_op_threads: int = 1
    #: onnxruntime's idle threads spin-wait after each run by default; on a shared CPU that
    #: steals the cores the pre- and post-processing (and the calibrator) need next.
    allow_spinning: bool = False


class OnnxRunner:
    """Loads ``model_path`` for CPU inference and runs it on one float32 input."""

    def __init__(self, model_path: str | Path, params: RunnerParams = RunnerParams(),
                 input_name: str | None = None, output_name: str | None = None) -> None:
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model not found: {path}")
        if params.threads < 0:
            raise ValueError(f"threads must be >= 0, got {params.threads}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = params.threads
        options.inter_op_num_threads = params.inter_op_threads
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        spin = "1" if params.allow_spinning else "0"
        options.add_session_config_entry("session.intra_op.allow_spinning", spin)
        options.add_session_config_entry("session.inter_op.allow_spinning", spin)
        try:
            self.session = ort.InferenceSession(str(path), sess_options=options,
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ValueError(f"{path}: not a loadable ONNX model ({exc})") from None
        self.path = path
        self.input = _pick(self.session.get_inputs(), input_name, "input", path)
        self.output = _pick(self.session.get_outputs(), output_name, "output", path)
        if self.input.type != "tensor(float)":
            raise ValueError(f"{path}: input '{self.input.name}' is {self.input.type}; "
                             "semcal_ros feeds tensor(float) (export the model with float32 input)")

    def check_input(self, expected: Sequence[int], meaning: str) -> None:
        """Raise if the declared input shape cannot take ``expected`` (``meaning`` explains it)."""
        declared = list(self.input.shape)
        if not shape_fits(declared, expected):
            raise ValueError(f"{self.path}: input '{self.input.name}' has shape "
                             f"{_fmt(declared)} but the model config gives {list(expected)} "
                             f"({meaning})")

    def check_output(self, expected: Sequence[int | None], meaning: str,
                     shape: Sequence[Dim] | None = None) -> None:
        """Raise if the output shape (declared, or ``shape`` as produced) does not fit.

        ``None`` in ``expected`` accepts any size (e.g. logits at a quarter of the input size).
        """
        actual = list(self.output.shape if shape is None else shape)
        if not shape_fits(actual, expected):
            want = ["any" if e is None else e for e in expected]
            raise ValueError(f"{self.path}: output '{self.output.name}' has shape "
                             f"{_fmt(actual)} but the model config expects {want} ({meaning})")

    def check_segmentation_output(self, kind: str, num_classes: int,
                                  size: tuple[int | None, int | None] = (None, None),
                                  shape: Sequence[int] | None = None) -> None:
        """Raise unless the output is ``logits`` (1 x C x h x w, float) or a ``class_map``
        (1 x h x w or 1 x 1 x h x w, integer). ``size`` = (h, w) it must have (None: any);
        ``shape`` is that of a produced output, else the declared one is checked (if known)."""
        actual = self.output.shape if shape is None else list(shape)
        if actual is None:  # rank unknown until the model runs
            return
        if kind == "logits":
            expected = [1, num_classes, *size]
            meaning = f"logits N x C x H x W with C = {num_classes} entries in 'classes'"
        else:
            expected = [1, 1, *size] if len(actual) == 4 else [1, *size]
            meaning = "class map N x H x W (or N x 1 x H x W)"
        want = "float" if kind == "logits" else "int"
        if shape is None and want not in self.output.type:
            other = "class_map" if kind == "logits" else "logits"
            raise ValueError(f"{self.path}: output '{self.output.name}' is {self.output.type}, "
                             f"but output: {kind} needs {want} values (output: {other}?)")
        self.check_output(expected, meaning, actual)

    def run(self, tensor: np.ndarray) -> np.ndarray:
        """The selected output for one input tensor (float32, shape checked beforehand)."""
        return self.session.run([self.output.name], {self.input.name: tensor})[0]


def shape_fits(declared: Sequence[Dim], expected: Sequence[int | None]) -> bool:
    """Same rank, and every dimension known on both sides equal."""
    if len(declared) != len(expected):
        return False
    return all(not isinstance(d, int) or e is None or d == e for d, e in zip(declared, expected))


def _pick(nodes: list, name: str | None, what: str, path: Path):
    if name is not None:
        for node in nodes:
            if node.name == name:
                return node
        raise ValueError(f"{path}: the model has no {what} named '{name}' "
                         f"(it has: {', '.join(n.name for n in nodes)})")
    if len(nodes) != 1:
        names = ", ".join(n.name for n in nodes)
        raise ValueError(f"{path}: the model has {len(nodes)} {what}s ({names}); "
                         f"set {what}_name in the model config")
    return nodes[0]


def _fmt(shape: Sequence[Dim]) -> str:
    return "[" + ", ".join("?" if d is None else str(d) for d in shape) + "]"
