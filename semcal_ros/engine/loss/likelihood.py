"""The labels' likelihood under the confusion between map and label classes (``kind:
likelihood``, the default) and its prior-free form, mutual information (``kind: mi``).

Real segmenters err in whole regions of a consistently confused class (hedge = terrain, shadowed
hedge = building) rather than in noise; a colour distance charges such a region in full at the
truth, and a pose that hides it wins.

- ``mi``: the conditional entropy of the label given the rendered class, H(T | R) / H(T) = 1 -
  MI(R; T) / H(T), from the joint histogram of rendered and labelled classes over every valid
  target pixel ("nothing rendered" is a rendered class of its own, so looking away is not free).
  A consistent confusion still carries information, so it still aligns; but MI cannot tell which
  class should match which (after swapping two classes the histogram is as informative: on a
  real frame started at the truth, ``mi`` moved 9 m to where the map's road lay on the image's
  buildings).
- ``likelihood``: -mean log C[rendered, label] / H(T), with C the joint histogram's rows (the
  confusion matrix at this pose) shrunk towards a prior that puts weight on the diagonal and on
  the confusions real segmenters and point labellers make (``CONFUSIONS``): a swap costs, a
  consistent confusion (facades the point labeller calls vegetation) still aligns.
- ``em: true`` (Dempster, Laird & Rubin 1977): the refinement stages hold the confusion fixed,
  estimated at each stage's start (the E step), and minimise the labels' cost under it (the M
  step). Re-estimated at every pose, C absorbs part of a misalignment (a flat basin) and its
  fixed shrinkage caps what agreement earns, which moves the minimum off the truth on clean labels.
  With ``em_prior_pixels`` the held confusion is learned from the frame (a Dirichlet prior of that
  many pixels per class, so the frame's evidence outweighs it as it grows) and a pixel costs the
  log-likelihood ratio of its label under the rendered class against under the matching one
  (:func:`learned_costs`), with the colour loss's boundary band: clean labels give a
  near-diagonal C and L2's sharpness, a real confusion stays cheap, swaps stay dear.
"""

from __future__ import annotations

import numba
import numpy as np

from semcal_ros.engine.labels import INVALID, SKY
from semcal_ros.engine.loss.band import class_distances
from semcal_ros.engine.loss.params import N_CLASSES, LossParams
from semcal_ros.engine.loss.pixels import EXPECTED, TABLE, cost_sum, mean_cost

#: Pairs of classes real segmenters and point labellers confuse with each other (measured on the
#: shared KITTI and PJLab frames, docs/real-data.md): the likelihood's prior gives them weight.
CONFUSIONS = (("terrain", "vegetation"), ("building", "vegetation"), ("sky", "building"),
              ("sidewalk", "road"), ("wall", "building"), ("fence", "building"),
              ("fence", "vegetation"), ("pole", "traffic sign"), ("pole", "traffic light"),
              ("terrain", "sidewalk"), ("car", "truck"))


def likelihood_reference(rendered: np.ndarray, target: np.ndarray, params: LossParams,
                  probabilities: np.ndarray | None) -> tuple[float, float]:
    """H(T | R) / H(T) from the joint histogram, in numpy (the reference for the kernel)."""
    top = int(round(params.crop_top * target.shape[0]))
    r = rendered[top:].ravel().astype(np.int64)
    t = target[top:].ravel().astype(np.int64)
    ok = t != INVALID
    scene = ok & (t != SKY)
    n_scene = int(scene.sum())
    coverage = float((scene & (r != INVALID)).sum()) / n_scene if n_scene else 0.0
    def histogram(keep: np.ndarray) -> np.ndarray:
        rows = np.where(r == INVALID, N_CLASSES, r)[keep]
        joint = np.zeros((N_CLASSES + 1, N_CLASSES))
        if probabilities is None:
            np.add.at(joint, (rows, t[keep]), 1.0)
        else:
            np.add.at(joint, rows, probabilities[top:].reshape(-1, N_CLASSES)[keep])
        return joint

    joint = histogram(ok)
    # H(T) is always over every valid pixel; left-out pixels leave only the histogram
    h_all = _label_entropy(joint)
    if params.blind_rows > 0:
        joint = histogram(ok & ~below_map_mask(rendered, params.blind_rows)[top:].ravel())
    if joint.sum() == 0 or coverage < params.min_coverage:
        return params.degenerate_loss, coverage
    scale = _label_entropy(joint) / h_all if h_all > 0 else 0.0
    if params.kind == "likelihood":
        return likelihood_share(joint, confusion_prior(params.confusion_weight),
                                params.prior_weight) * scale, coverage
    return conditional_entropy_share(joint) * scale, coverage


def _label_entropy(joint: np.ndarray) -> float:
    """H(T) of a joint histogram's label columns (0 for an empty one): the normaliser of every
    histogram loss here."""
    cols = np.asarray(joint, float).sum(axis=0)
    n = cols.sum()
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(-np.sum(np.where(cols > 0, cols * np.log(cols / n), 0.0)) / n) if n else 0.0


def below_map_mask(rendered: np.ndarray, blind_rows: float = 1.0) -> np.ndarray:
    """bool (H, W): in the lowest ``blind_rows`` share of the rows, the pixels below the lowest
    one the map draws in their column (a column it draws nothing in: all of them).
    ``loss.blind_rows`` leaves them out of the likelihood's histogram: a lidar sees no ground
    closer than its lowest beam reaches (a top-mounted one: 5-9 m ahead), the camera does, and
    counting that road as "nothing drawn" rewards a view from too high that spreads the map's
    nearest rings over it. The share bounds what a view can leave out: drawn high in the image
    (from too low), the map would otherwise leave half the image out of the judgement."""
    drawn = np.asarray(rendered) != INVALID
    h = drawn.shape[0]
    lowest = np.where(drawn.any(axis=0), h - 1 - np.argmax(drawn[::-1], axis=0), -1)
    rows = np.arange(h)[:, None]
    return (rows > lowest[None, :]) & (rows >= h - int(round(blind_rows * h)))


def confusion_prior(confusion_weight: float) -> np.ndarray:
    """float64[N_CLASSES + 1, N_CLASSES]: per rendered class (last row: nothing rendered), the
    prior distribution of the label there: the class itself (1), the classes it is usually
    confused with (``confusion_weight``); nothing rendered is sky. Rows sum to 1."""
    from semcal_ros.engine.labels import CITYSCAPES_ID

    prior = np.zeros((N_CLASSES + 1, N_CLASSES))
    prior[np.arange(N_CLASSES), np.arange(N_CLASSES)] = 1.0
    for a, b in CONFUSIONS:
        i, j = CITYSCAPES_ID[a], CITYSCAPES_ID[b]
        prior[i, j] = prior[j, i] = confusion_weight
    prior[N_CLASSES, SKY] = 1.0
    return prior / prior.sum(axis=1, keepdims=True)


def likelihood_share(joint: np.ndarray, prior: np.ndarray, weight: float) -> float:
    """-mean log C[rendered, label] / H(T), with C the joint histogram's rows (the confusion
    matrix at this pose) shrunk towards ``prior``: C = (row share + weight x prior) / (1 +
    weight). ``weight`` 0 gives H(T | R) / H(T) (mutual information); with a weight, a class drawn
    where the labels have another costs what the prior says of that pair, so a pose that maps
    road onto building no longer scores as well as the truth (mutual information does not see
    which class matches which)."""
    joint = np.asarray(joint, float)
    n = joint.sum()
    conf = shrunk_confusion(joint, prior, weight)
    with np.errstate(divide="ignore", invalid="ignore"):
        cost = -np.sum(np.where(joint > 0, joint * np.log(np.where(joint > 0, conf, 1.0)), 0.0))
    h_t = _label_entropy(joint)
    return float(cost / n / h_t) if h_t > 0 else 0.0


#: the learned confusion's smallest probability: a pair never seen at the stage's start (and
#: not a usual confusion) costs log(C[t, t] / 1e-3), about 7, not an unbounded amount
LEARNED_FLOOR = 1e-3


def learned_costs(joint: np.ndarray, prior: np.ndarray, pseudo: float) -> np.ndarray:
    """float64[N_CLASSES + 1, N_CLASSES]: the adaptive likelihood's cost of rendered class r
    (last row: nothing rendered) where the labels say t, from the confusion the frame itself
    shows at a pose (EM's E step): C[r] = (joint[r] + pseudo x prior[r]) / (n_r + pseudo), a
    Dirichlet prior of ``pseudo`` pixels per rendered class, so the frame's evidence outweighs
    it as it grows. The cost is the log-likelihood ratio of label t under r against under the
    class that matches t (t itself; nothing rendered for sky), clipped at 0: a match costs 0,
    a confusion the frame makes often costs little (facades as vegetation: C 0.4 against 0.9,
    0.8), a swap or a pair the frame never shows about 7. On clean labels C is near-diagonal and
    every mismatch costs alike (the paper's L2 with its boundary band, in shape); the fixed
    shrinkage of :func:`shrunk_confusion` instead caps what agreement earns."""
    joint = np.asarray(joint, float)
    rows = joint.sum(axis=1, keepdims=True)
    conf = (joint + pseudo * prior) / np.maximum(rows + pseudo, 1e-12)
    logc = np.log(np.maximum(conf, LEARNED_FLOOR))
    ref = logc[np.arange(N_CLASSES), np.arange(N_CLASSES)].copy()
    ref[SKY] = logc[N_CLASSES, SKY]
    costs = np.maximum(ref[None, :] - logc, 0.0)
    costs[np.arange(N_CLASSES), np.arange(N_CLASSES)] = 0.0  # a match (sky drawn is one too)
    return costs


def shrunk_confusion(joint: np.ndarray, prior: np.ndarray, weight: float) -> np.ndarray:
    """C = (row share of ``joint`` + weight x prior) / (1 + weight): the confusion matrix at a
    pose shrunk towards the prior; a row nothing was drawn in is the prior's."""
    rows = joint.sum(axis=1, keepdims=True)
    share = joint / np.where(rows > 0, rows, 1.0)
    return np.where(rows > 0, (share + weight * prior) / (1.0 + weight), prior)


def conditional_entropy_share(joint: np.ndarray) -> float:
    """H(T | R) / H(T) of a joint histogram (rows R, columns T): 0 when the rendered class
    decides the label, 1 when it says nothing about it (1 - normalised mutual information)."""
    joint = np.asarray(joint, float)
    n = joint.sum()
    rows = joint.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        h_cond = -np.sum(np.where(joint > 0, joint * np.log(joint / rows), 0.0)) / n
    h_t = _label_entropy(joint)
    return float(h_cond / h_t) if h_t > 0 else 0.0


#: the ``mi`` loss is the likelihood with no prior
_NO_PRIOR = np.zeros((N_CLASSES + 1, N_CLASSES))
_NO_COSTS = np.zeros((1, 1), np.uint16)  # the pixel kernel's unused argument


@numba.njit(cache=True, nogil=True)
def _joint_kernel(rendered, target, start, joint, probabilities, soft, width, blind_from):
    """The joint histogram of rendered (row N_CLASSES = nothing rendered) and labelled classes
    over the valid target pixels, soft (``probabilities[p]``) or by the target class. Pixels
    from row ``blind_from`` on (of rows ``width`` wide) that lie below the lowest one the map
    draws in their column are left out of the histogram, not of the coverage
    (:func:`below_map_mask`). Returns (scene pixels, those covered)."""
    n = target.shape[0]
    stop = max(start, min(blind_from * width, n))  # the rows no pixel is left out of
    lowest = np.full(width, -1, np.int64)
    if stop < n:
        for p in range(n):
            if rendered[p] != INVALID:
                lowest[p % width] = p // width
    n_scene, n_covered = _joint_rows(rendered, target, start, stop, joint, probabilities, soft,
                                     width, lowest, False)
    s2, c2 = _joint_rows(rendered, target, stop, n, joint, probabilities, soft, width, lowest,
                         True)
    return n_scene + s2, n_covered + c2


@numba.njit(cache=True, nogil=True, inline="always")
def _joint_rows(rendered, target, first, end, joint, probabilities, soft, width, lowest, blind):
    """:func:`_joint_kernel` over pixels ``first`` to ``end``; ``blind``: leave out those below
    ``lowest`` in their column (a loop of its own, so the usual one does no division)."""
    n_scene = 0
    n_covered = 0
    for p in range(first, end):
        t = target[p]
        if t == INVALID:
            continue
        r = rendered[p]
        if t != SKY:
            n_scene += 1
            if r != INVALID:
                n_covered += 1
        if blind and p // width > lowest[p % width]:
            continue
        row = N_CLASSES if r == INVALID else r
        if soft:
            for k in range(N_CLASSES):
                joint[row, k] += probabilities[p, k]
        else:
            joint[row, t] += 1.0
    return n_scene, n_covered


@numba.njit(cache=True, nogil=True)
def _likelihood(joint, prior, weight, h_target):
    """The kernel of :func:`likelihood_share` (``h_target`` precomputed); with ``weight`` 0 it
    is H(T | R) / H(T), the ``mi`` loss."""
    n = 0.0
    h = 0.0
    for r in range(joint.shape[0]):
        nr = 0.0
        for t in range(joint.shape[1]):
            nr += joint[r, t]
        if nr <= 0:
            continue
        n += nr
        for t in range(joint.shape[1]):
            c = joint[r, t]
            if c > 0:
                h -= c * np.log((c / nr + weight * prior[r, t]) / (1.0 + weight))
    return h / n / h_target if n > 0 and h_target > 0 else 0.0


class LikelihoodCost:
    """The likelihood (or ``mi``) of one target: the joint histogram at each pose, or the
    confusion held by :meth:`freeze` (``em``)."""

    table = None  # no class-pair table: the costs come from the histogram

    def __init__(self, target: np.ndarray, shape: tuple[int, int], start: int,
                 params: LossParams, scale: int, probabilities: np.ndarray | None) -> None:
        self.target, self.shape, self.start, self.params = target, shape, start, params
        self.scale = scale
        self.band_px = params.boundary_band_px / scale
        self.prior = confusion_prior(params.confusion_weight) if params.kind == "likelihood" \
            else None
        # the learned confusion's per-pixel costs held by freeze (None: re-estimated at each
        # pose), and the learned loss's share of the loss while held
        self.learned: np.ndarray | None = None
        self.share = 0.0
        self.dist = np.zeros((1, 1), np.uint8)  # the band's class distances, at first need
        self.soft = probabilities is not None
        self.probabilities = (np.ascontiguousarray(probabilities.reshape(-1, N_CLASSES),
                                                   dtype=np.float32)
                              if probabilities is not None else np.zeros((1, N_CLASSES),
                                                                         np.float32))
        # H(T) over the (fixed) valid pixels: the normaliser of H(T | R)
        joint = np.zeros((N_CLASSES + 1, N_CLASSES))
        _joint_kernel(np.full(target.shape, INVALID, np.uint8), target, start, joint,
                      self.probabilities, self.soft, shape[1], shape[0])
        # the first row whose pixels may lie in the lidar's blind zone
        self.blind_from = shape[0] - int(round(params.blind_rows * shape[0]))
        self.h_target = _label_entropy(joint)

    def _joint(self, flat: np.ndarray) -> tuple[np.ndarray, int, int]:
        joint = np.zeros((N_CLASSES + 1, N_CLASSES))
        n_scene, n_covered = _joint_kernel(flat, self.target, self.start, joint,
                                           self.probabilities, self.soft, self.shape[1],
                                           self.blind_from)
        return joint, n_scene, n_covered

    def freeze(self, flat: np.ndarray) -> None:
        """The E step at ``flat``: the frame's confusion learned there (:func:`learned_costs`)
        and held until :meth:`thaw`, trusted as far as the labels agree with the map there
        (``em_agreement``: the share of the learned loss, the rest the likelihood re-estimated
        at each pose). Clean labels get the learned costs alone: every mismatch costs alike and
        the minimum sits where L2's does (the re-estimated likelihood's lies a few cm off on
        ideal labels: its fixed shrinkage caps what agreement earns and pixels no point covers
        count). A real segmenter's labels keep the tolerant likelihood, which the learned costs
        lost to on real frames (the evidence in docs/engine.md)."""
        if self.prior is None:
            return
        joint, _, _ = self._joint(flat)
        drawn = joint[:N_CLASSES].sum()
        agreement = float(np.trace(joint[:N_CLASSES]) / drawn) if drawn > 0 else 0.0
        lo, hi = self.params.em_agreement
        self.share = float(np.clip((agreement - lo) / (hi - lo), 0.0, 1.0))
        if self.share <= 0.0:
            self.learned = None
            return
        pseudo = self.params.em_prior_pixels / (self.scale * self.scale)
        self.learned = learned_costs(joint, self.prior, pseudo)
        if self.band_px > 0 and self.dist.shape[0] != N_CLASSES:
            self.dist = class_distances(self.target.reshape(self.shape), self.band_px)

    def thaw(self) -> None:
        """Back to the likelihood re-estimated at every pose."""
        self.learned = None
        self.share = 0.0

    def evaluate(self, flat: np.ndarray) -> tuple[float, float]:
        if self.learned is not None:
            sharp, coverage, judged = mean_cost(cost_sum(
                flat, self.target, self.start, self.learned, N_CLASSES, self.dist,
                self.band_px > 0, _NO_COSTS, self.probabilities,
                EXPECTED if self.soft else TABLE, 1.0), self.params, self.h_target)
            if not judged or self.share >= 1.0:
                return float(sharp), coverage
            tolerant, _ = self._reestimated(flat)
            return self.share * float(sharp) + (1.0 - self.share) * tolerant, coverage
        return self._reestimated(flat)

    def _reestimated(self, flat: np.ndarray) -> tuple[float, float]:
        """The likelihood (or ``mi``) with the confusion estimated at this pose."""
        joint, n_scene, n_covered = self._joint(flat)
        n = joint.sum()
        coverage = n_covered / n_scene if n_scene else 0.0
        if coverage < self.params.min_coverage or n == 0:
            return self.params.degenerate_loss, coverage
        if self.prior is not None:
            return float(_likelihood(joint, self.prior, self.params.prior_weight,
                                     self.h_target)), coverage
        return float(_likelihood(joint, _NO_PRIOR, 0.0, self.h_target)), coverage
