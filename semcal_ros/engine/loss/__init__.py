"""The loss between the map's rendered labels and the camera's label image, one module per kind.

``engine.loss.kind`` chooses (``LOSS_KINDS``): ``likelihood`` (the default) and ``mi`` in
likelihood.py, the paper's ``l2`` and ``huber`` in colour.py, ``balanced`` in balanced.py (the
boundary band they share: band.py). Each
kind is a cost object with ``evaluate``, ``freeze`` and ``thaw``; :class:`LabelLoss` holds the
target once and hands a rendered image to its kind. probabilities.py: a segmenter's softmax as
the target; outliers.py: label errors left out of a second refinement.
"""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.labels import INVALID
from semcal_ros.engine.loss.balanced import balanced_table
from semcal_ros.engine.loss.band import class_distances
from semcal_ros.engine.loss.colour import ColourCost, colour_reference, pair_table
from semcal_ros.engine.loss.likelihood import (
    CONFUSIONS, LEARNED_FLOOR, LikelihoodCost, conditional_entropy_share, confusion_prior,
    learned_costs, likelihood_reference, likelihood_share, shrunk_confusion,
)
from semcal_ros.engine.loss.outliers import label_outliers
from semcal_ros.engine.loss.params import LOSS_KINDS, N_CLASSES, LossParams
from semcal_ros.engine.loss.probabilities import (
    COST_UNIT, aligned_probabilities, expected_costs, read_probabilities,
)

#: the kinds computed from the joint histogram of rendered and labelled classes
HISTOGRAM_KINDS = ("mi", "likelihood")


class LabelLoss:
    """The loss against one target image, ready to be evaluated many times. ``scale`` is the
    image's downsampling factor: the boundary band is given in full-resolution pixels.
    ``probabilities``: (H, W, N_CLASSES) aligned class probabilities of the target (from
    :func:`aligned_probabilities`), the expected cost instead of the argmax's."""

    def __init__(self, target_aligned: np.ndarray, params: LossParams, scale: int = 1,
                 probabilities: np.ndarray | None = None) -> None:
        self.params = params
        self.shape = target_aligned.shape
        self.target = np.ascontiguousarray(target_aligned, dtype=np.uint8).ravel()
        self.start = int(round(params.crop_top * self.shape[0])) * self.shape[1]
        self.band_px = params.boundary_band_px / scale  # the boundary band at this resolution
        if probabilities is not None and probabilities.shape != self.shape + (N_CLASSES,):
            raise ValueError(f"probabilities {probabilities.shape} do not fit the labels "
                             f"{self.shape}")
        self.cost: ColourCost | LikelihoodCost
        if params.kind in HISTOGRAM_KINDS:
            self.cost = LikelihoodCost(self.target, self.shape, self.start, params, scale,
                                       probabilities)
        else:
            table = (balanced_table(self.target) if params.kind == "balanced"
                     else pair_table(params.kind, params.huber_delta))
            self.cost = ColourCost(self.target, self.shape, self.start, params, scale,
                                   probabilities, table)
        self.table = self.cost.table  # the class-pair table of a colour kind, else None

    def __call__(self, rendered: np.ndarray) -> float:
        return self.evaluate(rendered)[0]

    def _flat(self, rendered: np.ndarray) -> np.ndarray:
        if rendered.shape != self.shape:
            raise ValueError(f"rendered image {rendered.shape} != target {self.shape}")
        return np.ascontiguousarray(rendered).ravel()

    def evaluate(self, rendered: np.ndarray) -> tuple[float, float]:
        """(loss, coverage of the target's non-sky pixels by rendered points)."""
        return self.cost.evaluate(self._flat(rendered))

    def freeze(self, rendered: np.ndarray) -> None:
        """EM's E step at ``rendered`` (the likelihood with ``em``; nothing for other kinds)."""
        self.cost.freeze(self._flat(rendered))

    def thaw(self) -> None:
        self.cost.thaw()

    def floor(self, rendered: np.ndarray) -> float:
        """The loss ``rendered`` would have if every pixel it covers drew its label's class: what
        no pose can beat with this coverage. 0 for the paper's L2; above 0 for the losses whose
        confusion matrix is shrunk towards a prior (a perfect match still pays -log C[c, c] < 1)
        and for any loss counting the pixels nothing covers. The verdict measures a loss rise
        above this floor, so a floor does not widen the uncertainty it reports."""
        drawn = np.asarray(rendered).reshape(self.shape)
        target = self.target.reshape(self.shape)
        perfect = np.where((drawn != INVALID) & (target != INVALID), target, drawn)
        return self.evaluate(perfect)[0]


def loss_reference(rendered: np.ndarray, target: np.ndarray, table: np.ndarray | None,
                   params: LossParams, band_px: float | None = None,
                   probabilities: np.ndarray | None = None) -> tuple[float, float]:
    """(loss, coverage) in numpy, the reference for the kernels; ``target`` holds aligned
    classes (INVALID = ignore), ``table`` the colour kinds' class-pair table. ``band_px``: the
    boundary band at this image's resolution (default ``params``'); ``probabilities``: (H, W,
    N_CLASSES) aligned class probabilities (the expected cost)."""
    if params.kind in HISTOGRAM_KINDS:
        return likelihood_reference(rendered, target, params, probabilities)
    assert table is not None, "a colour kind needs its class-pair table"
    return colour_reference(rendered, target, table, params, band_px, probabilities)


__all__ = ["CONFUSIONS", "COST_UNIT", "HISTOGRAM_KINDS", "LEARNED_FLOOR", "LOSS_KINDS",
           "N_CLASSES", "LabelLoss", "LossParams", "aligned_probabilities", "balanced_table",
           "class_distances", "conditional_entropy_share", "confusion_prior", "expected_costs",
           "label_outliers", "learned_costs", "likelihood_share", "loss_reference", "pair_table",
           "read_probabilities", "shrunk_confusion"]
