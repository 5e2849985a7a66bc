"""The boundary band (``loss.boundary_band_px``): how far each pixel lies from each class of the
labels. A rendered class within the band of where the labels have it costs in proportion to that
distance (a label boundary drawn a few pixels off costs little, and the loss near the optimum is
quadratic instead of V-shaped); the colour losses, the learned likelihood and soft targets all
use it."""

from __future__ import annotations

import cv2
import numpy as np

from semcal_ros.engine.loss.params import N_CLASSES


def class_distances(target: np.ndarray, band_px: float) -> np.ndarray:
    """uint8[N_CLASSES, H*W]: per class, the distance from each pixel to the nearest target pixel
    of that class, as a share of ``band_px`` (255 = the band or farther). One OpenCV distance
    transform per class present; absent classes are 255 everywhere."""
    h, w = target.shape
    out = np.full((N_CLASSES, h * w), 255, np.uint8)
    for c in np.unique(target):
        if c >= N_CLASSES:
            continue
        dist = cv2.distanceTransform((target != c).astype(np.uint8), cv2.DIST_L2, 5)
        out[c] = np.minimum(dist.ravel() * (255.0 / band_px), 255.0).astype(np.uint8)
    return out
