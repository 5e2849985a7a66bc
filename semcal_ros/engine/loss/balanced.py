"""The class-balanced mismatch (``kind: balanced``), after Chen & Sun 2026's class-matched
divergence: every mismatch costs alike, each label class weighted by the inverse of its share,
so swaps cost, but so does every confusion (measured: worse than the likelihood on real labels).
It runs on the colour loss's kernel (colour.py) with the table below."""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.labels import INVALID, SKY
from semcal_ros.engine.loss.colour import pair_table


def balanced_table(target: np.ndarray) -> np.ndarray:
    """float64[256, 256]: the ``balanced`` loss's cost of rendered class r where the labels say
    t: 0 when they agree, else the weight of t, the inverse of its share of the labelled pixels
    over the number of classes present (each class weighs alike, however few its pixels: poles
    and signs count as much as the road). Sky keeps weight 1 (it is where the map is not)."""
    t = target[target != INVALID]
    counts = np.bincount(t, minlength=256).astype(np.float64)
    present = counts > 0
    weight = np.ones(256)
    if present.any():
        share = counts / counts.sum()
        weight[present] = 1.0 / (share[present] * present.sum())
    weight[SKY] = 1.0
    table = pair_table("balanced") * weight[None, :]
    return table
