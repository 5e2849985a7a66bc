"""Voxel downsampling that keeps a class per voxel (the majority of the points inside).

Open3D's voxel filter averages colours but has no notion of a label; averaging class ids would
invent classes. Here every voxel keeps the centroid of the points of its most frequent class, so
class boundaries stay sharp and each output point lies on a surface of its class.
"""

from __future__ import annotations

import numpy as np


def voxel_majority(xyz: np.ndarray, labels: np.ndarray, voxel: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: (M, 3) float64 centroids and (M,) majority labels.

    Ties between classes go to the smaller class id (deterministic).
    """
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    labels = np.asarray(labels)
    if len(labels) == 0:
        return np.zeros((0, 3)), np.zeros(0, labels.dtype)
    classes = np.flatnonzero(np.bincount(labels.astype(np.int64)))
    index_of = np.zeros(int(classes[-1]) + 1, np.int64)
    index_of[classes] = np.arange(len(classes))
    label_index = index_of[labels]
    origin = np.asarray(xyz).min(axis=0).astype(np.float64)
    local = (np.asarray(xyz) - origin).astype(np.float32)  # small numbers: float32 is exact enough
    cells = np.floor(local / np.float32(voxel)).astype(np.int64)
    span = cells.max(axis=0) + 1
    if np.prod(span.astype(float)) * len(classes) >= 2.0 ** 62:
        raise ValueError("cloud too large for this voxel size")
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    combined = key * len(classes) + label_index
    order = np.argsort(combined)
    combined = combined[order]
    starts = np.flatnonzero(np.r_[True, combined[1:] != combined[:-1]])
    groups = combined[starts]
    counts = np.diff(np.r_[starts, len(combined)])
    sums = np.add.reduceat(local[order], starts, axis=0, dtype=np.float64)
    group_voxel = groups // len(classes)
    # within each voxel (groups are sorted by voxel, then class), take the most frequent class
    rank = np.lexsort((-counts, group_voxel))
    first = np.r_[True, group_voxel[rank][1:] != group_voxel[rank][:-1]]
    best = rank[first]
    return sums[best] / counts[best, None] + origin, classes[groups[best] % len(classes)]
