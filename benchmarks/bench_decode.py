"""What a compressed camera stream costs: bytes per frame and decode time per frame.

A roadside camera (1920x1200) publishes ``image_raw/compressed``; ``image_segmenter`` and the
calibrator decode each frame they take (:mod:`semcal_ros.io.images`, OpenCV). This prints, per
form: bytes per frame (against 6.9 MB raw rgb8), encode time (the driver's side) and decode time
(ours, through the ROS adapter on a real ``sensor_msgs/CompressedImage``), median and 90th
percentile, plus the machine's load. The frame is a real 1920x1200 roadside picture
(/work/shared/data/pjlab_lidar_camera/ours1/calib.jpg) when present, else a synthetic one; the
label image is that picture quantised to the Cityscapes palette (regions like a segmenter's).

    .venv/bin/python benchmarks/bench_decode.py [--repeats 50] [--image FILE]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2
import numpy as np

from semcal_ros.io import images
from semcal_ros.engine.labels import CITYSCAPES_PALETTE

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "pjlab_lidar_camera" / "ours1" / "calib.jpg"


def frame(path: Path | None) -> tuple[np.ndarray, str]:
    """(1920x1200 RGB, where it came from)."""
    if path is not None and path.is_file():
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr.shape[:2] != (1200, 1920):
            bgr = cv2.resize(bgr, (1920, 1200), interpolation=cv2.INTER_AREA)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), str(path)
    rng = np.random.default_rng(0)
    small = rng.integers(0, 255, (75, 120, 3), dtype=np.uint8)
    smooth = cv2.resize(small, (1920, 1200), interpolation=cv2.INTER_CUBIC)
    noise = rng.normal(0, 4, smooth.shape)
    return np.clip(smooth + noise, 0, 255).astype(np.uint8), "synthetic (no real image found)"


def quantised_labels(rgb: np.ndarray) -> np.ndarray:
    """Class ids of the nearest Cityscapes colour, cleaned by a median filter."""
    palette = np.asarray([CITYSCAPES_PALETTE[i] for i in range(19)], np.int32)
    small = cv2.resize(rgb, (480, 300), interpolation=cv2.INTER_AREA).astype(np.int32)
    d = ((small[:, :, None, :] - palette[None, None]) ** 2).sum(-1)
    labels = d.argmin(-1).astype(np.uint8)
    labels = cv2.medianBlur(labels, 5)
    return cv2.resize(labels, (1920, 1200), interpolation=cv2.INTER_NEAREST)


def timed(fn, repeats: int) -> tuple[float, float]:
    """(median, 90th percentile) in ms."""
    fn()  # warm
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(t)), float(np.percentile(t, 90))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--image", type=Path, default=REAL)
    args = ap.parse_args()
    from semcal_ros.ros.compressed import compressed_image, to_labels, to_rgb
    from semcal_ros.ros.conversions import make_header, numpy_to_image

    rgb, source = frame(args.image)
    labels = quantised_labels(rgb)
    header = make_header("camera_optical", 0.0)
    print(f"frame: {source}, {rgb.shape[1]}x{rgb.shape[0]}; OpenCV {cv2.__version__}, "
          f"{cv2.getNumThreads()} OpenCV threads; load before {os.getloadavg()}")
    raw = numpy_to_image(rgb, "rgb8", header)
    ms, p90 = timed(lambda: to_rgb(raw), args.repeats)
    print(f"{'raw rgb8 (no decode, a view)':34s} {len(raw.data) / 1e6:7.2f} MB  "
          f"decode {ms:6.2f} ms (p90 {p90:6.2f})")
    rows = [("camera JPEG q95", rgb, "jpeg", "rgb8", to_rgb, 95),
            ("camera JPEG q80", rgb, "jpeg", "rgb8", to_rgb, 80),
            ("camera PNG level 3", rgb, "png", "rgb8", to_rgb, 95),
            ("labels PNG level 3 (mono8)", labels, "png", "mono8", to_labels, 95)]
    for name, img, codec, encoding, decode, quality in rows:
        enc_ms, _ = timed(lambda: images.encode(img, codec, encoding, jpeg_quality=quality),
                          max(args.repeats // 5, 5))
        msg = compressed_image(img, codec, encoding, header, jpeg_quality=quality)
        ms, p90 = timed(lambda: decode(msg), args.repeats)
        out = decode(msg)
        error = np.abs(out.astype(np.int16) - img).mean()
        print(f"{name:34s} {len(msg.data) / 1e6:7.2f} MB  decode {ms:6.2f} ms (p90 {p90:6.2f})"
              f"  encode {enc_ms:6.1f} ms  mean |error| {error:.2f}")
    print(f"load after {os.getloadavg()}")


if __name__ == "__main__":
    main()
