"""``semcal export-model``: a real Cityscapes segmenter as ONNX, from its published weights.

Builds ESPNetv2 or ESPNet from a ``.npz`` of the authors' PyTorch state_dict, or the EdgeTPU
DeepLab from its dequantised ``.npz`` and ``.graph.json`` operator list (no PyTorch or TensorFlow
needed), and writes the model config beside it, ready for ``semcal segment-image`` and the
``image_segmenter`` node. See docs/real-data.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    from semcal_ros.segmentation.export import ARCH_NAMES, DEFAULT_SIZES

    parser = subparsers.add_parser(
        "export-model", help="build a real Cityscapes segmenter (ESPNetv2, ESPNet, EdgeTPU DeepLab) as ONNX",
        description="Rebuild a published Cityscapes segmentation network as an ONNX graph from "
                    "its weights (.npz of the PyTorch state_dict) and write its model config "
                    "YAML beside it (same name, .yaml).")
    parser.add_argument("arch", choices=ARCH_NAMES, help="network architecture")
    parser.add_argument("--weights", required=True, type=Path, help=".npz weights file")
    parser.add_argument("--out", required=True, type=Path, help="ONNX file to write (.onnx)")
    sizes = ", ".join(f"{a} {w}x{h}" for a, (w, h) in DEFAULT_SIZES.items())
    parser.add_argument("--width", type=int, help=f"network input width (default: {sizes})")
    parser.add_argument("--height", type=int, help="network input height (default: as above)")
    parser.add_argument("--graph", type=Path,
                        help="edgetpu_deeplab: its operator list (default: X.graph.json beside "
                             "X.npz)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import time

    from semcal_ros.segmentation.export.exporter import export_model

    start = time.perf_counter()
    result = export_model(args.arch, args.weights, args.out, args.width, args.height,
                          args.graph)
    folded = (f"{result.folded_batchnorms} BatchNorms folded into convolutions, "
              if result.folded_batchnorms else "")
    print(f"{args.arch}: {result.parameters:,} parameters, {result.nodes} nodes, {folded}"
          f"{result.width}x{result.height} input, built in {time.perf_counter() - start:.1f} s\n"
          f"  model:  {result.model_path}\n  config: {result.config_path}")
    return 0
