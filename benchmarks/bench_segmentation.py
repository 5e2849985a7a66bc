"""Runner overhead of the segmenters, apart from the model's own time.

Targets (issue 5): pre- plus post-processing <= 15 ms per 1024x512 image and <= 20 ms per
120k-point scan. The models are the tests' 1x1-convolution models (test/onnx_models.py) shaped
like the example configs in config/models/ (19 Cityscapes classes at 1024x512; 20 SemanticKITTI
classes at 64x2048), so the overhead is what a real model of that shape would see; their model
time is that of a trivial network and says nothing about a real one.

Inputs are real when /work/shared/data (or --data) holds them: a KITTI object image (resized to
1024x512, and at its native 1242x375, which adds a resize) and a KITTI odometry scan (~124k points).

    .venv/bin/python benchmarks/bench_segmentation.py [--repeats 30] [--threads 0]

With ``--image-model M.onnx --image-config C.yaml`` it times that (real) model instead, e.g. an
export of ``semcal export-model espnetv2``, on KITTI odometry 00 frame 0 (1241x376): the time a
frame waits, model included.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "test"))

from onnx_models import colour_model, range_channel_model  # noqa: E402

from semcal_ros.engine.labels import CITYSCAPES_PALETTE  # noqa: E402
from semcal_ros.segmentation.cloud import CloudSegmenter, check_scan  # noqa: E402
from semcal_ros.segmentation.image import ImageSegmenter  # noqa: E402
from semcal_ros.segmentation.model_config import load_model_config  # noqa: E402
from semcal_ros.segmentation.onnx_runner import OnnxRunner, RunnerParams  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
IMAGE_CONFIG = ROOT / "config" / "models" / "ocrnet_cityscapes.yaml"
RANGE_CONFIG = ROOT / "config" / "models" / "salsanext_semantickitti.yaml"


def timed(fn, *args):
    """Result, wall ms and CPU ms (all threads of this process) of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, ((time.perf_counter() - wall) * 1e3, (time.process_time() - cpu) * 1e3)


def report(name: str, rows: list[tuple[tuple[float, float], ...]]) -> None:
    """Median and 90th percentile of wall time, median CPU time, per stage."""
    arr = np.array(rows)  # runs x stage (pre, model, post) x (wall, cpu)
    stages = {"preprocess": arr[:, 0], "postprocess": arr[:, 2],
              "overhead": arr[:, 0] + arr[:, 2], "model": arr[:, 1], "total": arr.sum(axis=1)}
    print(f"{name}\n  {len(rows)} runs      wall median (p90) ms   CPU median ms")
    for label, values in stages.items():
        wall, cpu = values[:, 0], values[:, 1]
        print(f"  {label:12s} {np.median(wall):8.2f} ({np.percentile(wall, 90):7.2f})"
              f"   {np.median(cpu):8.2f}")


def tiny_model_segmenter(workdir: Path, params: RunnerParams) -> ImageSegmenter:
    """The 1x1-convolution colour model shaped like the OCRNet example config."""
    config = load_model_config(IMAGE_CONFIG)
    palette = np.array([CITYSCAPES_PALETTE[i] for i in range(config.num_classes)])
    model = colour_model(workdir / "image.onnx", palette, config.input_width, config.input_height,
                         channel_order=config.channel_order, scale=config.scale, mean=config.mean,
                         std=config.std)
    return ImageSegmenter(OnnxRunner(model, params), config)


def bench_image(seg: ImageSegmenter, image: np.ndarray, name: str, repeats: int) -> None:
    config = seg.config
    rows = []
    for i in range(repeats + 3):
        tensor, t_pre = timed(seg.preprocess, image, "rgb8")
        output, t_model = timed(seg.infer, tensor)
        labels, t_post = timed(seg.postprocess, output, image.shape[:2])
        if i >= 3:  # the first runs compile the argmax kernel and warm onnxruntime
            rows.append((t_pre, t_model, t_post))
    assert labels.shape == image.shape[:2]
    report(f"image {name} {image.shape[1]}x{image.shape[0]} -> model "
           f"{config.input_width}x{config.input_height}, {config.num_classes} classes", rows)


def bench_cloud(workdir: Path, scan: np.ndarray, name: str, repeats: int,
                params: RunnerParams) -> None:
    config = load_model_config(RANGE_CONFIG)
    # 20 height bands: a model of the example config's shape whose labels are easy to check
    centres = np.linspace(-2.5, 4.0, config.num_classes)
    model = range_channel_model(workdir / "range.onnx", 3, centres, config.means[3],
                                config.stds[3], config.height, config.width)
    seg = CloudSegmenter(OnnxRunner(model, params), config)
    xyz, intensity = check_scan(scan[:, :3], scan[:, 3])
    rows = []
    for i in range(repeats + 3):
        (tensor, proj), t_pre = timed(seg.preprocess, xyz, intensity)
        output, t_model = timed(seg.infer, tensor)
        labels, t_post = timed(seg.postprocess, output, xyz, proj)
        if i >= 3:
            rows.append((t_pre, t_model, t_post))
    lost = len(proj.lost())
    assert len(labels) == len(xyz)
    report(f"scan {name}: {len(xyz)} points ({lost} lost their pixel) -> "
           f"{config.height}x{config.width}, {config.num_classes} classes", rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--threads", type=int, default=0, help="onnxruntime threads (0: all)")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--image-model", type=Path, help="time this ONNX image model instead")
    parser.add_argument("--image-config", type=Path, help="its model config (kind: image)")
    args = parser.parse_args()
    params = RunnerParams(threads=args.threads)
    if args.image_model is not None:
        if args.image_config is None:
            parser.error("--image-model needs --image-config")
        frame = args.data / "kitti_odometry_00" / "image_2" / "000000.png"
        image = cv2.cvtColor(cv2.imread(str(frame)), cv2.COLOR_BGR2RGB)
        seg = ImageSegmenter.from_files(args.image_model, args.image_config, params)
        bench_image(seg, image, f"{args.image_model.name} on {frame.name}", args.repeats)
        return 0
    image_path = args.data / "kitti_object" / "tr_000000.png"
    scan_path = args.data / "kitti_odometry_00" / "velodyne" / "000000.bin"
    if image_path.is_file():
        native = cv2.cvtColor(cv2.imread(str(image_path)), cv2.COLOR_BGR2RGB)
        name = image_path.name
    else:
        print(f"{image_path} not found: using a random image")
        native = np.random.default_rng(0).integers(0, 256, (375, 1242, 3), dtype=np.uint8)
        name = "random"
    if scan_path.is_file():
        scan = np.fromfile(scan_path, dtype=np.float32).reshape(-1, 4)
        scan_name = scan_path.name
    else:
        print(f"{scan_path} not found: using 120k random points")
        rng = np.random.default_rng(0)
        scan = np.column_stack([rng.normal(0, 20, (120_000, 3)), rng.random(120_000)])
        scan_name = "random"
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        resized = cv2.resize(native, (1024, 512), interpolation=cv2.INTER_LINEAR)
        seg = tiny_model_segmenter(workdir, params)
        bench_image(seg, resized, name, args.repeats)
        bench_image(seg, native, name, args.repeats)
        bench_cloud(workdir, scan, scan_name, args.repeats, params)
    return 0


if __name__ == "__main__":
    sys.exit(main())
