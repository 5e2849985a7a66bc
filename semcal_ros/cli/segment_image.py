"""``semcal segment-image``: label one camera image with an ONNX model (Cityscapes trainIds).

Writes the label image the calibrator reads (mono8 trainIds, 255 = ignored) and, on request, an
overlay picture to check the segmentation by eye and the class probabilities (``.npz``, key
``probabilities``, float16 (H, W, 19), pixel-aligned with the labels; docs/CONTRACTS.md).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "segment-image", help="label an image with an ONNX model (Cityscapes trainIds)",
        description="Run an ONNX image segmentation model (configured by a model config YAML, "
                    "see config/models/) on one 8-bit colour image and write its Cityscapes "
                    "trainId label image.")
    parser.add_argument("--model", required=True, type=Path, help="ONNX model file")
    parser.add_argument("--model-config", required=True, type=Path,
                        help="model config YAML (kind: image)")
    parser.add_argument("image", type=Path, metavar="IMAGE", help="8-bit colour image (png, jpg)")
    parser.add_argument("--out", required=True, type=Path, help="label image to write (.png)")
    parser.add_argument("--overlay", type=Path, help="also write the labels over the image")
    parser.add_argument("--probabilities", type=Path, metavar="OUT.npz",
                        help="also write the class probabilities (softmax over trainIds 0-18, "
                             "float16 H x W x 19, key 'probabilities'; needs a logits model)")
    parser.add_argument("--threads", type=int, default=0,
                        help="onnxruntime threads (default 0: all cores)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from semcal_ros.io.files import write_label_image, write_rgb_image
    from semcal_ros.engine.labels import CITYSCAPES
    from semcal_ros.segmentation.decode import class_shares
    from semcal_ros.segmentation.image import ImageSegmenter, label_overlay, read_colour_image
    from semcal_ros.segmentation.onnx_runner import RunnerParams
    from semcal_ros.segmentation.probabilities import write_probabilities

    segmenter = ImageSegmenter.from_files(args.model, args.model_config,
                                          RunnerParams(threads=args.threads))
    image, encoding = read_colour_image(args.image)
    start = time.perf_counter()
    if args.probabilities is not None:
        labels, probabilities = segmenter.segment_with_probabilities(image, encoding)
    else:
        labels = segmenter.segment(image, encoding)
    seconds = time.perf_counter() - start
    write_label_image(args.out, labels)
    if args.probabilities is not None:
        write_probabilities(args.probabilities, probabilities)
    if args.overlay is not None:
        rgb = image[:, :, 2::-1]  # OpenCV's BGR(A) -> RGB
        write_rgb_image(args.overlay, label_overlay(rgb, labels))
    print(f"{args.image}: {image.shape[1]}x{image.shape[0]} labelled in {seconds * 1e3:.0f} ms "
          f"-> {args.out}" + (f" and {args.probabilities}" if args.probabilities else "")
          + f"\n  {class_shares(labels, CITYSCAPES)}")
    return 0
