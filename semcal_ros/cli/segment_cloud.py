"""``semcal segment-cloud``: label one lidar scan with an ONNX range-image model or, with
``--method geometric``, with the network-free geometric labeller
(:mod:`semcal_ros.segmentation.geometric`).

Reads a PLY (x, y, z and optionally intensity), a PCD or a KITTI ``.bin`` scan and writes the engine's
labelled PLY (float x, y, z, float intensity when known, ushort label = SemanticKITTI id).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from semcal_ros.segmentation.labellers import POINT_LABELLERS

#: PLY vertex properties read as the intensity channel, first match wins.
INTENSITY_FIELDS = ("intensity", "remission", "reflectance")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "segment-cloud", help="label a lidar scan (ONNX range-image model or geometric rules)",
        description="Label every point of one scan with its SemanticKITTI class and write it: "
                    "--method onnx (default) runs an ONNX range-image segmentation model "
                    "(RangeNet++/SalsaNext convention, configured by a model config YAML, see "
                    "config/models/); --method geometric needs no model (ground segmentation, "
                    "shape rules; docs/segmentation.md).")
    parser.add_argument("--method", choices=tuple(POINT_LABELLERS), default="onnx",
                        help="onnx (needs --model, --model-config) or geometric (no model)")
    parser.add_argument("--model", type=Path, help="ONNX model file (--method onnx)")
    parser.add_argument("--model-config", type=Path,
                        help="model config YAML (kind: range) (--method onnx)")
    parser.add_argument("--config", type=Path,
                        help="--method geometric: a ROS parameter file whose cloud_segmenter "
                             "'geometric:' group overrides the labeller's thresholds "
                             "(default: the built-in values = config/cloud_segmenter.yaml)")
    parser.add_argument("scan", type=Path, metavar="SCAN",
                        help="scan: .ply with x, y, z[, intensity], .pcd, or KITTI .bin")
    parser.add_argument("--out", required=True, type=Path, help="labelled PLY to write")
    parser.add_argument("--threads", type=int, default=0,
                        help="onnxruntime threads (default 0: all cores)")
    parser.set_defaults(func=run)


def read_scan_file(path: Path):
    """(xyz (N, 3), intensity (N,) or None) of a .ply or KITTI .bin scan."""
    from semcal_ros.io import kitti, pcd, ply

    suffix = path.suffix.lower()
    if suffix == ".bin":
        cloud = kitti.read_scan(path)
    elif suffix == ".ply":
        cloud = ply.read_ply(path, require_label=False)  # names a missing x, y or z
    elif suffix == ".pcd":
        cloud = pcd.read_pcd(path)
    else:
        raise ValueError(f"{path}: unknown scan format '{suffix}' "
                         f"(expected .ply, .pcd or KITTI .bin)")
    intensity = next((cloud.extra[f] for f in INTENSITY_FIELDS if f in cloud.extra), None)
    return cloud.xyz, intensity


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from semcal_ros.engine.cloud import LabelledCloud
    from semcal_ros.io.ply import write_ply
    from semcal_ros.engine.labels import SEMANTIC_KITTI
    from semcal_ros.segmentation.decode import class_shares
    from semcal_ros.segmentation.labellers import make_labeller
    from semcal_ros.segmentation.onnx_runner import RunnerParams

    geometric = None
    if not POINT_LABELLERS[args.method].needs_model:
        from semcal_ros.segmentation.geometric import params_from_file

        geometric = params_from_file(args.config)
    elif args.model is None or args.model_config is None:
        raise ValueError(f"--method {args.method} needs --model and --model-config "
                         "(or use --method geometric)")
    segment = make_labeller(args.method, args.model, args.model_config,
                            RunnerParams(threads=args.threads), geometric)
    xyz, intensity = read_scan_file(args.scan)
    start = time.perf_counter()
    labels = segment(xyz, intensity)
    seconds = time.perf_counter() - start
    extra = {} if intensity is None else {"intensity": np.asarray(intensity, dtype=np.float32)}
    write_ply(args.out, LabelledCloud(xyz, labels, extra))
    print(f"{args.scan}: {len(labels)} points labelled in {seconds * 1e3:.0f} ms -> {args.out}"
          f"\n  {class_shares(labels, SEMANTIC_KITTI)}")
    return 0
