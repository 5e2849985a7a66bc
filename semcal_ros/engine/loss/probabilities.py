"""A segmenter's class probabilities as the target: a pixel the network was unsure of costs less.

The colour losses charge a pixel its expected distance under the softmax (precomputed per
rendered class as uint16, :func:`expected_costs`); the likelihood fills its histogram with the
probabilities instead of one count. ``semcal real-scene --probabilities`` writes the file.
"""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.loss.band import class_distances
from semcal_ros.engine.loss.params import N_CLASSES

#: expected costs are stored as uint16 in units of the largest colour distance / 65535
COST_UNIT = 3.0 / 65535.0


def aligned_probabilities(probabilities: np.ndarray, image_lut: np.ndarray,
                          target: np.ndarray) -> np.ndarray:
    """float32 (H, W, N_CLASSES): a segmenter's softmax over Cityscapes trainIds 0-18 summed onto
    the aligned classes (``LabelMapping.image_lut``) and renormalised over the classes the
    loss can use; a pixel with (almost) no such mass keeps its target class with certainty."""
    p = np.asarray(probabilities, dtype=np.float32)
    if p.ndim != 3 or p.shape[2] != N_CLASSES or p.shape[:2] != target.shape:
        raise ValueError(f"probabilities must be (H, W, {N_CLASSES}) = "
                         f"{target.shape + (N_CLASSES,)}, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("probabilities contain NaN or infinite values")
    out = np.zeros(p.shape, np.float32)
    for train_id in range(N_CLASSES):
        a = int(image_lut[train_id])
        if a < N_CLASSES:
            out[..., a] += p[..., train_id]
    mass = out.sum(axis=2, keepdims=True)
    sure = np.zeros_like(out)
    t = target.astype(np.int64)
    ok = t < N_CLASSES
    sure[ok, t[ok]] = 1.0
    weak = mass < 1e-3
    out = np.where(weak, sure, out / np.maximum(mass, 1e-3))
    return out


def read_probabilities(path) -> np.ndarray:
    """float32 (H, W, 19) from a ``probabilities.npz`` (key ``probabilities``: a segmenter's
    softmax over Cityscapes trainIds 0-18, the size of labels.png), written by
    ``semcal real-scene --probabilities``; one clear line for a file that is not one."""
    try:
        with np.load(path) as data:
            keys = list(data.files)
            p = data["probabilities"] if "probabilities" in keys else None
    except (OSError, EOFError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz file "
                         f"({' '.join(str(exc).split())[:80]})") from None
    if p is None:
        raise ValueError(f"{path}: no 'probabilities' array (keys: {', '.join(keys) or 'none'})")
    if p.ndim != 3 or p.shape[2] != N_CLASSES:
        raise ValueError(f"{path}: probabilities must be (H, W, {N_CLASSES}), got {p.shape}")
    return p.astype(np.float32)


def expected_costs(probabilities: np.ndarray, table: np.ndarray, target: np.ndarray,
                   band: float) -> np.ndarray:
    """uint16[N_CLASSES, H*W] in units of ``COST_UNIT``: per rendered class the expected cost
    of each pixel under the aligned class probabilities (with the boundary band: times the
    rendered class's distance share in the labels, as for the argmax target)."""
    h, w, _ = probabilities.shape
    q = probabilities.reshape(-1, N_CLASSES)
    costs = (q @ table[:N_CLASSES, :N_CLASSES].T.astype(np.float32)).T  # (rendered, pixel)
    if band > 0:
        costs = costs * (class_distances(target, band).astype(np.float32) / 255.0)
    return np.clip(np.rint(costs / COST_UNIT), 0, 65535).astype(np.uint16)
