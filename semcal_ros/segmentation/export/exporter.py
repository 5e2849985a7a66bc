"""export_model: weights .npz -> ONNX graph + model config YAML (see the package doc)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import onnx
import yaml

from semcal_ros.engine.labels import CITYSCAPES
from semcal_ros.segmentation.export import (ARCH_NAMES, DEFAULT_SIZES, edgetpu_deeplab, espnet,
                                            espnetv2)
from semcal_ros.segmentation.export.graph import Weights
from semcal_ros.segmentation.model_config import model_config_from_dict

#: Cityscapes trainIds 0-18 by name, then the models' background/void channel (ignored).
CLASSES_20: list[str | None] = [CITYSCAPES[i] for i in range(19)] + [None]
#: Cityscapes trainIds 0-18 by name (models without a background channel).
CLASSES_19: list[str | None] = CLASSES_20[:19]

@dataclass(frozen=True)
class Architecture:
    """One exportable network: its graph builder and its preprocessing facts."""

    build: Callable[[Weights, int, int], onnx.ModelProto]
    channel_order: str
    scale: float
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    note: str
    classes: tuple[str | None, ...] = tuple(CLASSES_20)
    outputs: str = "20 outputs, 19 = background (ignored)"


ARCHITECTURES: dict[str, Architecture] = {
    "espnetv2": Architecture(
        espnetv2.build, "RGB", 1.0 / 255.0, (0.485, 0.456, 0.406), (0.229, 0.224, 0.225),
        "ESPNetv2 (s=2.0) Cityscapes, sacmehta/EdgeNets: RGB in [0, 1], ImageNet mean/std"),
    "espnet": Architecture(
        espnet.build, "BGR", 1.0, (72.3923111, 82.90893555, 73.15840149),
        (45.3192215 * 255.0, 46.15289307 * 255.0, 44.91483307 * 255.0),
        "ESPNet (p=2, q=8) Cityscapes, sacmehta/ESPNet: BGR 0-255, (x - mean) / std / 255"),
    "edgetpu_deeplab": Architecture(
        edgetpu_deeplab.build, "RGB", 1.0, (128.0, 128.0, 128.0), (128.0, 128.0, 128.0),
        "DeepLab v3 MobileNet-EdgeTPU (x0.75) Cityscapes, google-coral/test_data int8 tflite "
        "dequantised: RGB, (x - 128) / 128, fully convolutional",
        tuple(CLASSES_19), "19 outputs = trainIds 0-18"),
}
assert tuple(ARCHITECTURES) == ARCH_NAMES



@dataclass(frozen=True)
class ExportResult:
    model_path: Path
    config_path: Path
    parameters: int
    folded_batchnorms: int
    nodes: int
    width: int
    height: int


def model_config(arch: str, width: int, height: int) -> dict[str, Any]:
    """The model config (``kind: image``) of an exported network, as written beside it."""
    a = ARCHITECTURES[arch]
    return {
        "kind": "image",
        "input_width": width,
        "input_height": height,
        "channel_order": a.channel_order,
        "scale": a.scale,
        "mean": list(a.mean),
        "std": list(a.std),
        "output": "logits",
        "classes": list(a.classes),
        "ignore": [],
    }


def config_path_for(model_path: str | Path) -> Path:
    """Where the model config goes: beside the model, same stem, ``.yaml``."""
    return Path(model_path).with_suffix(".yaml")


def export_model(arch: str, weights_path: str | Path, out: str | Path,
                 width: int | None = None, height: int | None = None,
                 graph: str | Path | None = None) -> ExportResult:
    """Build ``arch`` from ``weights_path``; write ``out`` (.onnx) and its model config.

    ``width`` / ``height`` default to the architecture's :data:`DEFAULT_SIZES`; ``graph`` is
    the EdgeTPU DeepLab's operator list (default: ``X.graph.json`` beside ``X.npz``).
    """
    if arch not in ARCHITECTURES:
        raise ValueError(f"unknown architecture '{arch}' (known: {', '.join(ARCHITECTURES)})")
    out = Path(out)
    if out.suffix != ".onnx":
        raise ValueError(f"{out}: the model file must end in .onnx")
    if graph is not None and arch != "edgetpu_deeplab":
        raise ValueError(f"--graph is for edgetpu_deeplab only ({arch} is built from its "
                         "weights alone)")
    width = DEFAULT_SIZES[arch][0] if width is None else width
    height = DEFAULT_SIZES[arch][1] if height is None else height
    a = ARCHITECTURES[arch]
    weights = Weights(weights_path, arch)
    if graph is not None:
        model = edgetpu_deeplab.build(weights, width, height, graph)
    else:
        model = a.build(weights, width, height)
    config = model_config(arch, width, height)
    model_config_from_dict(config)  # the runner will accept it
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(out))
    config_path = config_path_for(out)
    header = (f"# Model config of {out.name}, written by `semcal export-model {arch}`.\n"
              f"# {a.note}; {a.outputs}.\n")
    config_path.write_text(header + yaml.safe_dump(config, sort_keys=False, width=100,
                                                   default_flow_style=None))
    builder_stats = _stats(model)
    return ExportResult(out, config_path, weights.parameters, builder_stats[0], builder_stats[1],
                        width, height)


def _stats(model: onnx.ModelProto) -> tuple[int, int]:
    """(BatchNorms folded, nodes): folded ones are recorded in the model's metadata."""
    folded = next((int(p.value) for p in model.metadata_props if p.key == "folded_batchnorms"),
                  0)
    return folded, len(model.graph.node)
