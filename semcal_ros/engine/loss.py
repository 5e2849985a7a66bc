"""The paper's masked, beta-normalised loss, computed on integer label images.

Colours are a fixed function of labels, so the per-pixel colour distance is a lookup in a
class-pair table: no float colour images are ever built. The loss is the mean over valid pixels
(beta * sum / numel in the paper's notation), which gives the optimiser's tolerances a fixed meaning.

Validity, as in the paper's CARLA set-up: the target must carry a usable class; a pixel where no map
point landed is rendered as sky, which counts where the target is sky and is masked where it is not
(such holes come from map sparsity, not from a wrong pose).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from semcal_ros.engine.labels import INVALID, SKY, palette_array


#: The per-pixel costs, by parameter value, with the name tables print: the one list of them.
LOSS_KINDS = {"l2": "L2", "huber": "Huber"}


@dataclass(frozen=True)
class LossParams:
    kind: str = "l2"  # "l2" (squared colour distance) or "huber"
    huber_delta: float = 0.3
    crop_top: float = 0.0  # fraction of image rows, from the top, left out of the loss
    min_coverage: float = 0.05  # fewer rendered pixels over the target's non-sky area = degenerate
    degenerate_loss: float = 10.0  # loss of a view that shows (almost) none of the map
    # cost of a target pixel of a map class where no map point landed; 0 = masked (the paper).
    # Masking rewards views that show less of the map: a pose that renders only the easy road
    # wins over one that also renders the (imperfect) buildings and trees. A cost makes looking
    # away cost something too.
    uncovered_cost: float = 0.0
    # px (full resolution): a rendered class within this distance of where the target has that
    # class costs in proportion to the distance (a truncated distance transform of the target per
    # class); 0 = every mismatch costs in full (the paper). Boundaries a network drew a few pixels
    # off then cost little, and the loss near the optimum becomes quadratic instead of V-shaped.
    boundary_band_px: float = 4.0
    # px (full resolution): regions where the map and the labels disagree at the first result and
    # that are at least this wide (a morphological opening of the disagreement) are taken for
    # label errors (a blob of a wrong class, a missed object) and left out of a second refinement;
    # a pose error only makes thin bands along boundaries. 0 = off (the paper).
    outlier_width_px: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in LOSS_KINDS:
            raise ValueError(f"loss.kind must be one of {', '.join(LOSS_KINDS)}, not "
                             f"'{self.kind}'")
        if not 0.0 <= self.crop_top < 1.0:
            raise ValueError(f"loss.crop_top must be in [0, 1), got {self.crop_top}")
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"loss.min_coverage must be in [0, 1], got {self.min_coverage}")
        if not self.huber_delta > 0:
            raise ValueError(f"loss.huber_delta must be > 0, got {self.huber_delta}")
        if not self.degenerate_loss > 0:
            raise ValueError(f"loss.degenerate_loss must be > 0, got {self.degenerate_loss}")
        if not 0.0 <= self.uncovered_cost <= 3.0:  # 3 = the largest colour distance
            raise ValueError(f"loss.uncovered_cost must be in [0, 3], got {self.uncovered_cost}")
        if not 0.0 <= self.outlier_width_px <= 200.0:
            raise ValueError(f"loss.outlier_width_px must be in [0, 200], got "
                             f"{self.outlier_width_px}")
        if not 0.0 <= self.boundary_band_px <= 50.0:
            raise ValueError(f"loss.boundary_band_px must be in [0, 50], got "
                             f"{self.boundary_band_px}")


def pair_table(kind: str = "l2", delta: float = 0.3) -> np.ndarray:
    """float64[256, 256]: loss between the colours of two aligned classes (colours in [0, 1])."""
    colours = palette_array().astype(np.float64) / 255.0
    diff = colours[:, None, :] - colours[None, :, :]
    if kind == "l2":
        return np.sum(diff * diff, axis=2)
    a = np.abs(diff)
    huber = np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))
    return np.sum(huber, axis=2)


N_CLASSES = 19  # aligned classes are Cityscapes trainIds 0..18


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


def loss_reference(rendered: np.ndarray, target: np.ndarray, table: np.ndarray,
                   params: LossParams, band_px: float | None = None) -> tuple[float, float]:
    """(loss, coverage) in numpy; ``target`` holds aligned classes (INVALID = ignore).
    ``band_px``: the boundary band at this image's resolution (default ``params``')."""
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
    if band > 0:
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


@numba.njit(cache=True, nogil=True)
def _loss_kernel(rendered, target, table, start, dist, banded):
    """Sums over the valid pixels; with ``banded`` a mismatch is weighted by ``dist`` (the
    rendered class's distance in the target, 255 = the band or farther)."""
    total = 0.0
    n_valid = 0
    n_scene = 0
    n_covered = 0
    for p in range(start, target.shape[0]):
        t = target[p]
        if t == INVALID:
            continue
        r = rendered[p]
        if t != SKY:
            n_scene += 1
            if r == INVALID:
                continue
            n_covered += 1
        elif r == INVALID:
            r = SKY
        if banded:
            if r != t:
                total += table[r, t] * dist[r, p] * (1.0 / 255.0)
        else:
            total += table[r, t]
        n_valid += 1
    return total, n_valid, n_scene, n_covered


class LabelLoss:
    """The loss against one target image, ready to be evaluated many times. ``scale`` is the
    image's downsampling factor: the boundary band is given in full-resolution pixels."""

    def __init__(self, target_aligned: np.ndarray, params: LossParams, scale: int = 1) -> None:
        self.params = params
        self.shape = target_aligned.shape
        self.target = np.ascontiguousarray(target_aligned, dtype=np.uint8).ravel()
        self.table = pair_table(params.kind, params.huber_delta)
        self.start = int(round(params.crop_top * self.shape[0])) * self.shape[1]
        self.band_px = params.boundary_band_px / scale
        self.banded = self.band_px > 0
        self.dist = (class_distances(target_aligned, self.band_px) if self.banded
                     else np.zeros((1, 1), np.uint8))

    def __call__(self, rendered: np.ndarray) -> float:
        return self.evaluate(rendered)[0]

    def evaluate(self, rendered: np.ndarray) -> tuple[float, float]:
        """(loss, coverage of the target's non-sky pixels by rendered points)."""
        if rendered.shape != self.shape:
            raise ValueError(f"rendered image {rendered.shape} != target {self.shape}")
        total, n_valid, n_scene, n_covered = _loss_kernel(
            np.ascontiguousarray(rendered).ravel(), self.target, self.table, self.start,
            self.dist, self.banded)
        coverage = n_covered / n_scene if n_scene else 0.0
        if self.params.uncovered_cost > 0:
            n_valid += n_scene - n_covered
            total += self.params.uncovered_cost * (n_scene - n_covered)
        if n_valid == 0 or coverage < self.params.min_coverage:
            return self.params.degenerate_loss, coverage
        return total / n_valid, coverage


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
