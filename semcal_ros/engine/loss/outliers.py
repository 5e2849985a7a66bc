"""Label errors at a pose: wide regions where the map and the labels disagree
(``loss.outlier_width_px``), left out of a second refinement by the search."""

from __future__ import annotations

import cv2
import numpy as np

from semcal_ros.engine.labels import INVALID


def label_outliers(rendered: np.ndarray, target: np.ndarray, width_px: float,
                   grow_px: int = 2) -> np.ndarray:
    """bool mask of target pixels taken for label errors at a pose: where map and labels disagree
    over a region at least ``width_px`` wide (an opening with a disc of that diameter keeps those
    and drops the thin bands a small pose error draws along boundaries), grown by ``grow_px``."""
    disagree = (rendered != INVALID) & (target != INVALID) & (rendered != target)
    k = max(3, int(round(width_px)) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    wide = cv2.morphologyEx(disagree.astype(np.uint8), cv2.MORPH_OPEN, disc)
    if grow_px > 0 and wide.any():
        g = 2 * grow_px + 1
        wide = cv2.dilate(wide, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (g, g)))
    return wide.astype(bool)
