"""Segmentation-like errors for the ``noisy_labels`` variant.

A network's label image is wrong in two typical ways: class boundaries wander by a few pixels
(smoothly, not per pixel), and whole blobs get the wrong class. The first is a smooth random
displacement field applied with nearest-neighbour lookup; the second paints ellipses with the
class of a nearby different region (a plausible confusion, e.g. sidewalk as road).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class LabelNoise:
    jitter_px: float = 3.0  # typical boundary displacement (1-sigma of the field), pixels
    jitter_scale_px: float = 20.0  # correlation length of the displacement field
    blobs: int = 25
    blob_radius_px: tuple[float, float] = (6.0, 30.0)


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], scale: float) -> np.ndarray:
    """Zero-mean, unit-std smooth noise of the given correlation length.

    The mean is removed explicitly: blurred white noise keeps a sizeable random mean (0.1-0.3
    sigma here), which would shift the whole label image coherently, a bias a segmentation
    network does not have and one that reads as a rotation error of the camera.
    """
    field = rng.normal(0.0, 1.0, shape).astype(np.float32)
    field = cv2.GaussianBlur(field, (0, 0), scale)
    field -= field.mean()
    return field / max(float(field.std()), 1e-9)


def jitter_boundaries(labels: np.ndarray, rng: np.random.Generator, amount_px: float,
                      scale_px: float) -> np.ndarray:
    h, w = labels.shape
    dx = _smooth_field(rng, (h, w), scale_px) * amount_px
    dy = _smooth_field(rng, (h, w), scale_px) * amount_px
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(labels, gx + dx, gy + dy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def mislabel_blobs(labels: np.ndarray, rng: np.random.Generator, count: int,
                   radius_px: tuple[float, float]) -> np.ndarray:
    """Paint ``count`` ellipses, each with a class found a little outside it (never sky-only)."""
    out = labels.copy()
    h, w = labels.shape
    for _ in range(count):
        centre = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        axes = rng.uniform(*radius_px, 2)
        angle = rng.uniform(0, 180)
        probe = centre + rng.normal(0, 1, 2) * axes * 2.0
        px, py = np.clip(probe, 0, [w - 1, h - 1]).astype(int)
        here = labels[int(min(centre[1], h - 1)), int(min(centre[0], w - 1))]
        wrong = labels[py, px]
        if wrong == here:
            continue
        cv2.ellipse(out, (int(centre[0]), int(centre[1])), (int(axes[0]), int(axes[1])), angle,
                    0, 360, int(wrong), thickness=-1)
    return out


def add_label_noise(labels: np.ndarray, rng: np.random.Generator,
                    noise: LabelNoise = LabelNoise()) -> np.ndarray:
    jittered = jitter_boundaries(labels, rng, noise.jitter_px, noise.jitter_scale_px)
    return mislabel_blobs(jittered, rng, noise.blobs, noise.blob_radius_px)
