"""The paper's loss: the colour distance between the rendered and the labelled class.

Colours are a fixed function of labels, so the per-pixel colour distance is a lookup in a
class-pair table: no float colour images are ever built. The loss is the mean over valid pixels
(beta * sum / numel in the paper's notation), which gives the optimiser's tolerances a fixed meaning.

The valid pixels and the mean over them are pixels.py's (shared with the likelihood's learned
costs). ``l2`` (the paper's squared distance) and ``huber`` share this module; ``balanced``
(balanced.py) uses the same kernel with a table of its own. With the segmenter's class
probabilities as the target a pixel costs the expected distance under its softmax
(probabilities.py).
"""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.labels import INVALID, SKY, palette_array
from semcal_ros.engine.loss.band import class_distances
from semcal_ros.engine.loss.params import N_CLASSES, LossParams
from semcal_ros.engine.loss.pixels import PIXEL_COSTS, TABLE, cost_sum, mean_cost
from semcal_ros.engine.loss.probabilities import COST_UNIT, expected_costs


def pair_table(kind: str = "l2", delta: float = 0.3) -> np.ndarray:
    """float64[256, 256]: loss between the colours of two aligned classes (colours in [0, 1]);
    ``mi`` has no table (the L2 one is returned, used only by the reference's band)."""
    colours = palette_array().astype(np.float64) / 255.0
    diff = colours[:, None, :] - colours[None, :, :]
    if kind in ("l2", "mi", "likelihood"):
        return np.sum(diff * diff, axis=2)
    if kind == "balanced":  # per label class weights: :func:`balanced_table`
        return (np.arange(256)[:, None] != np.arange(256)[None, :]).astype(np.float64)
    a = np.abs(diff)
    huber = np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))
    return np.sum(huber, axis=2)


def colour_reference(rendered: np.ndarray, target: np.ndarray, table: np.ndarray,
                   params: LossParams, band_px: float | None = None,
                   probabilities: np.ndarray | None = None) -> tuple[float, float]:
    """(loss, coverage) in numpy; ``target`` holds aligned classes (INVALID = ignore).
    ``band_px``: the boundary band at this image's resolution (default ``params``');
    ``probabilities``: (H, W, N_CLASSES) aligned class probabilities (the expected cost)."""
    band = params.boundary_band_px if band_px is None else band_px
    if band > 0:
        table_px = _banded(rendered, target, table, band)
    top = int(round(params.crop_top * target.shape[0]))
    r = rendered[top:].ravel()
    t = target[top:].ravel()
    empty = r == INVALID
    valid = (t != INVALID) & (~empty | (t == SKY))
    r_eff = np.where(empty, SKY, r)
    scene = (t != INVALID) & (t != SKY)
    n_scene = int(scene.sum())
    uncovered = int((scene & empty).sum())
    coverage = float(n_scene - uncovered) / n_scene if n_scene else 0.0
    n_valid = int(valid.sum())
    if probabilities is not None:
        expected = expected_costs(probabilities, table, target, band)[:, top * target.shape[1]:]
        total = float(expected[r_eff[valid], np.nonzero(valid)[0]].sum()) * COST_UNIT
    elif band > 0:
        total = float(table_px[top * target.shape[1]:][valid].sum())
    else:
        total = float(table[r_eff[valid], t[valid]].sum())
    if params.uncovered_cost > 0:
        n_valid += uncovered
        total += params.uncovered_cost * uncovered
    if n_valid == 0 or coverage < params.min_coverage:
        return params.degenerate_loss, coverage
    return total / n_valid, coverage


def _banded(rendered: np.ndarray, target: np.ndarray, table: np.ndarray, band: float
            ) -> np.ndarray:
    """Per-pixel cost with the boundary band (numpy; the reference for the kernel)."""
    dist = class_distances(target, band)
    r = rendered.ravel().astype(np.int64)
    t = target.ravel().astype(np.int64)
    r_eff = np.where(r == INVALID, SKY, r)
    cost = np.zeros(r.shape, np.float64)
    ok = t != INVALID
    cost[ok] = table[r_eff[ok], t[ok]]
    near = ok & (r_eff < N_CLASSES)
    weight = np.ones(r.shape)
    weight[near] = dist[r_eff[near], np.nonzero(near)[0]] / 255.0
    return cost * weight


_NO_PROBABILITIES = np.zeros((1, N_CLASSES), np.float32)  # the kernel's unused argument


class ColourCost:
    """The colour-distance loss of one target (``l2``, ``huber``, ``balanced``): a class-pair
    table, the boundary band's per-class distances, or the expected costs of a soft target."""

    def __init__(self, target: np.ndarray, shape: tuple[int, int], start: int,
                 params: LossParams, scale: int, probabilities: np.ndarray | None,
                 table: np.ndarray) -> None:
        self.target, self.start, self.params, self.table = target, start, params, table
        band = params.boundary_band_px / scale
        self.banded = band > 0
        self.unit = COST_UNIT
        self.soft = probabilities is not None
        self.costs = np.zeros((1, 1), np.uint16)  # the expected costs of a soft target
        self.dist = np.zeros((1, 1), np.uint8)
        if probabilities is not None:
            self.costs = expected_costs(probabilities, table, target.reshape(shape),
                                        band if self.banded else 0.0)
        elif self.banded:
            self.dist = class_distances(target.reshape(shape), band)

    def evaluate(self, flat: np.ndarray) -> tuple[float, float]:
        loss, coverage, _ = mean_cost(cost_sum(
            flat, self.target, self.start, self.table, SKY, self.dist, self.banded, self.costs,
            _NO_PROBABILITIES, PIXEL_COSTS if self.soft else TABLE, self.unit), self.params)
        return loss, coverage

    def freeze(self, flat: np.ndarray) -> None:
        """Nothing to hold: the colour distances are fixed."""

    def thaw(self) -> None:
        """Nothing held."""
