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


# --- errors like a real network's --------------------------------------------------------------
@dataclass(frozen=True)
class NetworkNoise:
    """Label errors with the structure a real segmentation network's have (issue 12), rather
    than isotropic jitter: each class's boundary moves coherently over the whole image (a class is
    grown or shrunk, so the error is systematic, not zero-mean), thin classes by 1-3 px, small thin
    objects are missed, and whole parts of a class's regions take the class it is typically
    confused with (``confusion``: class -> ((other class, share of the class's area), ...)).
    ``KITTI_ESPNETV2`` holds the confusion measured on the real KITTI frame."""

    thin_classes: tuple[str, ...] = ("pole", "traffic sign", "traffic light", "fence")
    thin_shift_px: tuple[int, int] = (1, 3)  # per image and thin class: eroded or dilated by this
    shift_px: int = 2  # other classes: grown (+) or shrunk (-) by up to this, per image and class
    missed_area_px: int = 300  # thin-class components smaller than this may be missed ...
    missed_rate: float = 0.5  # ... each with this probability
    confusion: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = (
        ("vegetation", (("terrain", 0.1),)), ("fence", (("vegetation", 0.2),)),
        ("sidewalk", (("road", 0.1),)), ("building", (("vegetation", 0.05),)))
    confusion_radius_px: tuple[float, float] = (8.0, 40.0)
    blobs: int = 10  # wrong-class blobs anywhere (as LabelNoise's)
    blob_radius_px: tuple[float, float] = (6.0, 25.0)
    jitter_px: float = 1.5
    jitter_scale_px: float = 20.0


#: Confusion measured on KITTI odometry 00 frame 0: ESPNetv2 (Cityscapes weights) against the
#: projected SemanticKITTI labels of the scan (share of each true class's pixels given the other
#: class): docs/quality.md. Poles: 55 % building; vegetation: 33 % building, 22 % terrain; fence:
#: 60 % vegetation; sidewalk: 42 % road, 23 % building; traffic signs: missed.
KITTI_ESPNETV2 = NetworkNoise(
    missed_area_px=2000, missed_rate=1.0,
    confusion=(("vegetation", (("building", 0.33), ("terrain", 0.22))),
               ("pole", (("building", 0.55),)), ("fence", (("vegetation", 0.6),)),
               ("sidewalk", (("road", 0.42), ("building", 0.23))),
               ("building", (("vegetation", 0.08),)), ("car", (("building", 0.04),))))

NOISE_MODELS = {"network": NetworkNoise(), "kitti_espnetv2": KITTI_ESPNETV2}


def _grow(labels: np.ndarray, cls: int, px: int) -> np.ndarray:
    """``cls`` grown by ``px`` pixels (px > 0) or shrunk by -px, the freed pixels given the
    nearest other class."""
    from scipy.ndimage import distance_transform_edt

    mask = labels == cls
    if px == 0 or not mask.any() or mask.all():
        return labels
    out = labels.copy()
    if px > 0:
        out[(distance_transform_edt(~mask) <= px) & ~mask] = cls
    else:
        dist, (iy, ix) = distance_transform_edt(mask, return_indices=True)
        shrink = mask & (dist <= -px)
        out[shrink] = labels[iy[shrink], ix[shrink]]
    return out


def _miss_small(labels: np.ndarray, cls: int, area: int, rate: float,
                rng: np.random.Generator) -> np.ndarray:
    from scipy.ndimage import distance_transform_edt

    n, comp, stats, _ = cv2.connectedComponentsWithStats((labels == cls).astype(np.uint8), 8)
    drop = np.zeros(n, bool)
    drop[1:] = (stats[1:, cv2.CC_STAT_AREA] < area) & (rng.random(n - 1) < rate)
    gone = drop[comp]
    if not gone.any():
        return labels
    _, (iy, ix) = distance_transform_edt(gone, return_indices=True)
    out = labels.copy()
    out[gone] = labels[iy[gone], ix[gone]]
    return out


def _confuse(labels: np.ndarray, cls: int, other: int, share: float,
             radius_px: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Paint blobs of ``other`` inside ``cls``'s regions until about ``share`` of them is
    covered."""
    mask = labels == cls
    area = int(mask.sum())
    if area == 0 or share <= 0:
        return labels
    ys, xs = np.nonzero(mask)
    paint = np.zeros(labels.shape, np.uint8)
    for _ in range(400):
        if (paint & mask).sum() >= share * area:
            break
        k = rng.integers(len(ys))
        axes = rng.uniform(*radius_px, 2)
        cv2.ellipse(paint, (int(xs[k]), int(ys[k])), (int(axes[0]), int(axes[1])),
                    rng.uniform(0, 180), 0, 360, 1, thickness=-1)
    out = labels.copy()
    out[(paint > 0) & mask] = other
    return out


def add_network_noise(labels: np.ndarray, rng: np.random.Generator,
                      noise: NetworkNoise = NetworkNoise()) -> np.ndarray:
    """Cityscapes trainId label image with a network's kind of errors (see :class:`NetworkNoise`)."""
    from semcal_ros.engine.labels import CITYSCAPES, CITYSCAPES_ID

    out = labels.copy()
    present = [c for c in np.unique(labels) if int(c) in CITYSCAPES]
    thin = {CITYSCAPES_ID[n] for n in noise.thin_classes}
    for name, confusions in noise.confusion:
        for other, share in confusions:
            out = _confuse(out, CITYSCAPES_ID[name], CITYSCAPES_ID[other], share,
                           noise.confusion_radius_px, rng)
    for c in thin & set(int(v) for v in present):
        out = _miss_small(out, c, noise.missed_area_px, noise.missed_rate, rng)
    for c in rng.permutation(present):
        c = int(c)
        if c in thin:
            px = int(rng.integers(noise.thin_shift_px[0], noise.thin_shift_px[1] + 1))
            px *= 1 if rng.random() < 0.5 else -1
        else:
            px = int(rng.integers(-noise.shift_px, noise.shift_px + 1))
        out = _grow(out, c, px)
    out = jitter_boundaries(out, rng, noise.jitter_px, noise.jitter_scale_px)
    return mislabel_blobs(out, rng, noise.blobs, noise.blob_radius_px)


def noisy_labels(labels: np.ndarray, model: str, seed: int = 1) -> np.ndarray:
    """``labels`` with the errors of a named model: ``legacy`` (the ``noisy_labels`` variant's
    jitter and blobs) or a key of :data:`NOISE_MODELS`."""
    rng = np.random.default_rng(seed)
    if model == "legacy":
        return add_label_noise(labels, rng)
    if model not in NOISE_MODELS:
        raise ValueError(f"label noise must be legacy or one of {', '.join(NOISE_MODELS)}, "
                         f"not '{model}'")
    return add_network_noise(labels, rng, NOISE_MODELS[model])


def confusion_shares(predicted: np.ndarray, truth: np.ndarray, min_share: float = 0.04
                     ) -> dict[str, dict[str, float]]:
    """Per true class, the share of its (labelled) pixels a segmenter gave each other class, for
    shares of at least ``min_share``: how :data:`KITTI_ESPNETV2` was measured (ESPNetv2's labels of
    KITTI frame 0 against the scan's projected SemanticKITTI labels; docs/quality.md)."""
    from semcal_ros.engine.labels import CITYSCAPES, INVALID

    both = (predicted != INVALID) & (truth != INVALID)
    p, t = predicted[both].astype(np.int64), truth[both].astype(np.int64)
    out: dict[str, dict[str, float]] = {}
    for c in np.unique(t):
        if int(c) not in CITYSCAPES:
            continue
        counts = np.bincount(p[t == c], minlength=256) / max(int((t == c).sum()), 1)
        out[CITYSCAPES[int(c)]] = {CITYSCAPES[int(o)]: round(float(counts[o]), 3)
                                   for o in np.nonzero(counts >= min_share)[0]
                                   if o != c and int(o) in CITYSCAPES}
    return out
