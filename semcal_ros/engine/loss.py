"""The paper's masked, beta-normalised loss, computed on integer label images.

Colours are a fixed function of labels, so the per-pixel colour distance is a lookup in a
class-pair table: no float colour images are ever built. The loss is the mean over valid pixels
(beta * sum / numel in the paper's notation), which gives the optimiser's tolerances a fixed meaning.

Validity, as in the paper's CARLA set-up: the target must carry a usable class; a pixel where no map
point landed is rendered as sky, which counts where the target is sky and is masked where it is not
(such holes come from map sparsity, not from a wrong pose).

Two additions for real segmenters, whose errors are whole regions of a consistently confused
class (hedge = terrain, shadowed hedge = building) rather than noise:

- ``kind: mi`` (semantic mutual information): the loss is the conditional entropy of the label
  given the rendered class, H(T | R) / H(T) = 1 - MI(R; T) / H(T), from the joint histogram of
  rendered and labelled classes over every valid target pixel ("nothing rendered" is a rendered
  class of its own, so looking away is not free). A consistent confusion still carries
  information, so it still aligns; a pose that hides the mismatches loses information too.
- ``kind: likelihood`` (the default): -mean log C[rendered, label] / H(T), with C the joint
  histogram's rows (the confusion matrix between map and labels at this pose) shrunk towards a
  prior that puts weight on the diagonal and on the confusions real segmenters and point
  labellers make (``CONFUSIONS``). With no prior it is ``mi``; mutual information cannot tell
  which class should match which (after swapping two classes the histogram is as informative:
  on a real frame started at the truth, ``mi`` moved 9 m to where the map's road lay on the
  image's buildings); the prior makes a swap cost while a consistent confusion (facades the
  point labeller calls vegetation) still aligns. ``em: true`` holds C through each refinement
  stage (the E step at the stage's start) instead of re-estimating it at every pose.
- ``kind: balanced``: every mismatch costs alike, each label class weighted by the inverse of
  its share, after Chen & Sun 2026's class-balanced divergence: class-matched, so swaps cost,
  but every confusion costs in full (measured: worse than the likelihood on real labels).
- class probabilities as the target (``probabilities=`` of :class:`LabelLoss`): the cost of a
  pixel is the expected colour distance under the segmenter's own softmax (L2/Huber), or the
  histogram is filled with the probabilities (MI): a pixel the network was unsure of costs less.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from semcal_ros.engine.labels import INVALID, SKY, palette_array


#: The per-pixel costs, by parameter value, with the name tables print: the one list of them.
LOSS_KINDS = {"l2": "L2", "huber": "Huber", "mi": "MI", "likelihood": "Likelihood",
              "balanced": "Balanced"}

#: Pairs of classes real segmenters and point labellers confuse with each other (measured on the
#: shared KITTI and PJLab frames, docs/real-data.md): the likelihood's prior gives them weight.
CONFUSIONS = (("terrain", "vegetation"), ("building", "vegetation"), ("sky", "building"),
              ("sidewalk", "road"), ("wall", "building"), ("fence", "building"),
              ("fence", "vegetation"), ("pole", "traffic sign"), ("pole", "traffic light"),
              ("terrain", "sidewalk"), ("car", "truck"))


@dataclass(frozen=True)
class LossParams:
    kind: str = "likelihood"
    # "likelihood" (the mean log-likelihood of the labels under a confusion matrix estimated at
    # the pose, shrunk towards a prior that favours the diagonal and the usual confusions), "l2"
    # (squared colour distance, the paper's), "huber", "mi" (mutual information) or "balanced"
    # (every mismatch costs alike, each label class weighted by the inverse of its share: a
    # class-matched divergence balanced over classes, after Chen & Sun 2026)
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
    # likelihood: the prior's weight against the histogram's own rows (0 = mutual information,
    # blind to swapped classes; large = a fixed identity, blind to consistent confusions)
    prior_weight: float = 1.0
    # likelihood: a usual confusion's weight in the prior, against 1 on the diagonal
    confusion_weight: float = 0.3
    # likelihood: hold the confusion matrix fixed through each refinement stage, estimated at
    # the stage's start (EM); false = re-estimated at every pose
    em: bool = False
    # likelihood with em: the confusion learned at a stage's start is the frame's own histogram
    # plus this many pseudo-pixels of the prior per rendered class (full-resolution pixels;
    # a Dirichlet prior, so its weight falls as the class's evidence grows); 0 = shrunk by
    # ``prior_weight`` as at every pose
    em_prior_pixels: float = 0.0

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
        if not 0.0 <= self.prior_weight <= 100.0:
            raise ValueError(f"loss.prior_weight must be in [0, 100], got {self.prior_weight}")
        if not 0.0 <= self.confusion_weight <= 1.0:
            raise ValueError(f"loss.confusion_weight must be in [0, 1], got "
                             f"{self.confusion_weight}")
        if not 0.0 <= self.em_prior_pixels <= 1e6:
            raise ValueError(f"loss.em_prior_pixels must be in [0, 1e6], got "
                             f"{self.em_prior_pixels}")
        if not 0.0 <= self.boundary_band_px <= 50.0:
            raise ValueError(f"loss.boundary_band_px must be in [0, 50], got "
                             f"{self.boundary_band_px}")


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


N_CLASSES = 19  # aligned classes are Cityscapes trainIds 0..18


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
                   params: LossParams, band_px: float | None = None,
                   probabilities: np.ndarray | None = None) -> tuple[float, float]:
    """(loss, coverage) in numpy; ``target`` holds aligned classes (INVALID = ignore).
    ``band_px``: the boundary band at this image's resolution (default ``params``');
    ``probabilities``: (H, W, N_CLASSES) aligned class probabilities (the expected cost)."""
    if params.kind in ("mi", "likelihood"):
        return _mi_reference(rendered, target, params, probabilities)
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
        total = float(expected[r_eff[valid], np.nonzero(valid)[0]].sum()) * _COST_UNIT
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


def _mi_reference(rendered: np.ndarray, target: np.ndarray, params: LossParams,
                  probabilities: np.ndarray | None) -> tuple[float, float]:
    """H(T | R) / H(T) from the joint histogram, in numpy (the reference for the kernel)."""
    top = int(round(params.crop_top * target.shape[0]))
    r = rendered[top:].ravel().astype(np.int64)
    t = target[top:].ravel().astype(np.int64)
    ok = t != INVALID
    scene = ok & (t != SKY)
    n_scene = int(scene.sum())
    coverage = float((scene & (r != INVALID)).sum()) / n_scene if n_scene else 0.0
    rows = np.where(r == INVALID, N_CLASSES, r)[ok]
    joint = np.zeros((N_CLASSES + 1, N_CLASSES))
    if probabilities is None:
        np.add.at(joint, (rows, t[ok]), 1.0)
    else:
        q = probabilities[top:].reshape(-1, N_CLASSES)[ok]
        np.add.at(joint, rows, q)
    if joint.sum() == 0 or coverage < params.min_coverage:
        return params.degenerate_loss, coverage
    if params.kind == "likelihood":
        return likelihood_share(joint, confusion_prior(params.confusion_weight),
                                params.prior_weight), coverage
    return conditional_entropy_share(joint), coverage


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
    cols = joint.sum(axis=0)
    conf = shrunk_confusion(joint, prior, weight)
    with np.errstate(divide="ignore", invalid="ignore"):
        cost = -np.sum(np.where(joint > 0, joint * np.log(np.where(joint > 0, conf, 1.0)), 0.0))
        h_t = -np.sum(np.where(cols > 0, cols * np.log(cols / n), 0.0)) / n
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
    return np.maximum(ref[None, :] - logc, 0.0)


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
    cols = joint.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        h_cond = -np.sum(np.where(joint > 0, joint * np.log(joint / rows), 0.0)) / n
        h_t = -np.sum(np.where(cols > 0, cols * np.log(cols / n), 0.0)) / n
    return float(h_cond / h_t) if h_t > 0 else 0.0


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


#: the ``mi`` loss is the likelihood with no prior
_NO_PRIOR = np.zeros((N_CLASSES + 1, N_CLASSES))

#: expected costs are stored as uint16 in units of the largest colour distance / 65535
_COST_UNIT = 3.0 / 65535.0


def expected_costs(probabilities: np.ndarray, table: np.ndarray, target: np.ndarray,
                   band: float) -> np.ndarray:
    """uint16[N_CLASSES, H*W] in units of ``_COST_UNIT``: per rendered class the expected cost
    of each pixel under the aligned class probabilities (with the boundary band: times the
    rendered class's distance share in the labels, as for the argmax target)."""
    h, w, _ = probabilities.shape
    q = probabilities.reshape(-1, N_CLASSES)
    costs = (q @ table[:N_CLASSES, :N_CLASSES].T.astype(np.float32)).T  # (rendered, pixel)
    if band > 0:
        costs = costs * (class_distances(target, band).astype(np.float32) / 255.0)
    return np.clip(np.rint(costs / _COST_UNIT), 0, 65535).astype(np.uint16)


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


@numba.njit(cache=True, nogil=True)
def _cost_kernel(rendered, target, start, costs):
    """Sums of precomputed per-pixel costs (``costs[rendered class, pixel]``, uint16)."""
    total = 0
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
        total += costs[r, p]
        n_valid += 1
    return total, n_valid, n_scene, n_covered


@numba.njit(cache=True, nogil=True)
def _joint_kernel(rendered, target, start, joint, probabilities, soft):
    """The joint histogram of rendered (row N_CLASSES = nothing rendered) and labelled classes
    over the valid target pixels, soft (``probabilities[p]``) or by the target class."""
    n_scene = 0
    n_covered = 0
    for p in range(start, target.shape[0]):
        t = target[p]
        if t == INVALID:
            continue
        r = rendered[p]
        if t != SKY:
            n_scene += 1
            if r != INVALID:
                n_covered += 1
        row = N_CLASSES if r == INVALID else r
        if soft:
            for k in range(N_CLASSES):
                joint[row, k] += probabilities[p, k]
        else:
            joint[row, t] += 1.0
    return n_scene, n_covered


@numba.njit(cache=True, nogil=True)
def _learned_kernel(rendered, target, start, costs, dist, banded, uncovered):
    """Sum of :func:`learned_costs` over the valid target pixels and their count; with
    ``banded`` a rendered class's cost is weighted by its distance share in the labels
    (``dist``, 255 = the band or farther), as the L2 loss's. Pixels are valid as for the L2
    loss: a map-class pixel no point covers costs ``uncovered`` (0: masked, the paper), nothing
    drawn over sky is a match."""
    total = 0.0
    n = 0
    for p in range(start, target.shape[0]):
        t = target[p]
        if t == INVALID:
            continue
        r = rendered[p]
        if r == INVALID:
            if t != SKY:  # a map-class pixel no point covers: the L2 loss's rule
                if uncovered > 0:
                    n += 1
                    total += uncovered
                continue
            r = SKY  # nothing drawn where the labels have sky: a match
        n += 1
        if r != t:
            c = costs[r, t]
            if banded and c > 0:
                c *= dist[r, p] * (1.0 / 255.0)
            total += c
    return total, n


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
        self.table = (balanced_table(self.target) if params.kind == "balanced"
                      else pair_table(params.kind, params.huber_delta))
        self.start = int(round(params.crop_top * self.shape[0])) * self.shape[1]
        self.band_px = params.boundary_band_px / scale
        self.mi = params.kind in ("mi", "likelihood")  # both from the joint histogram
        self.prior = (confusion_prior(params.confusion_weight) if params.kind == "likelihood"
                      else None)
        self.frozen: np.ndarray | None = None  # -log C held fixed (freeze), or None
        # the learned confusion's per-pixel costs (freeze with em_prior_pixels), or None
        self.learned: np.ndarray | None = None
        self.scale = scale
        self.banded = self.band_px > 0 and not self.mi
        self.soft = probabilities is not None
        self.costs: np.ndarray | None = None
        self.probabilities = np.zeros((1, N_CLASSES), np.float32)
        self.dist = np.zeros((1, 1), np.uint8)
        if probabilities is not None:
            if probabilities.shape != self.shape + (N_CLASSES,):
                raise ValueError(f"probabilities {probabilities.shape} do not fit the labels "
                                 f"{self.shape}")
            if self.mi:
                self.probabilities = np.ascontiguousarray(
                    probabilities.reshape(-1, N_CLASSES), dtype=np.float32)
            else:
                self.costs = expected_costs(probabilities, self.table, target_aligned,
                                            self.band_px if self.banded else 0.0)
        elif self.banded:
            self.dist = class_distances(target_aligned, self.band_px)
        if self.mi:  # H(T) over the (fixed) valid pixels: the normaliser of H(T | R)
            joint = np.zeros((N_CLASSES + 1, N_CLASSES))
            _joint_kernel(np.full(self.target.shape, INVALID, np.uint8), self.target,
                          self.start, joint, self.probabilities, self.soft)
            cols = joint.sum(axis=0)
            n = cols.sum()
            self.h_target = float(-np.sum(np.where(cols > 0, cols * np.log(
                np.where(cols > 0, cols, 1.0) / max(n, 1.0)), 0.0)) / max(n, 1.0))

    def __call__(self, rendered: np.ndarray) -> float:
        return self.evaluate(rendered)[0]

    def freeze(self, rendered: np.ndarray) -> None:
        """The likelihood's E step: the confusion matrix estimated at ``rendered`` (shrunk
        towards the prior) is held fixed, and the loss becomes the mean of -log C[rendered,
        label] under it until :meth:`thaw`. With C re-estimated at every pose the loss absorbs
        part of a misalignment into C (a flat basin: 3-4 % per 25 cm on real frames); held
        fixed, a misplaced boundary costs what the labels at the estimate said it should."""
        if self.prior is None:
            return
        flat = np.ascontiguousarray(rendered).ravel()
        joint = np.zeros((N_CLASSES + 1, N_CLASSES))
        _joint_kernel(flat, self.target, self.start, joint, self.probabilities, self.soft)
        if self.params.em_prior_pixels > 0:
            pseudo = self.params.em_prior_pixels / (self.scale * self.scale)
            self.learned = learned_costs(joint, self.prior, pseudo)
            if self.band_px > 0 and not self.soft and self.dist.shape[0] != N_CLASSES:
                self.dist = class_distances(self.target.reshape(self.shape), self.band_px)
            return
        conf = shrunk_confusion(joint, self.prior, self.params.prior_weight)
        self.frozen = -np.log(np.maximum(conf, 1e-4))

    def thaw(self) -> None:
        """Back to the confusion matrix re-estimated at every pose."""
        self.frozen = self.learned = None

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

    def evaluate(self, rendered: np.ndarray) -> tuple[float, float]:
        """(loss, coverage of the target's non-sky pixels by rendered points)."""
        if rendered.shape != self.shape:
            raise ValueError(f"rendered image {rendered.shape} != target {self.shape}")
        flat = np.ascontiguousarray(rendered).ravel()
        if self.mi:
            joint = np.zeros((N_CLASSES + 1, N_CLASSES))
            n_scene, n_covered = _joint_kernel(flat, self.target, self.start, joint,
                                               self.probabilities, self.soft)
            coverage = n_covered / n_scene if n_scene else 0.0
            if coverage < self.params.min_coverage or joint.sum() == 0:
                return self.params.degenerate_loss, coverage
            if self.learned is not None:
                if self.soft:
                    return float(np.sum(joint * self.learned) / joint.sum()
                                 / self.h_target), coverage
                total, n = _learned_kernel(flat, self.target, self.start, self.learned,
                                           self.dist, self.band_px > 0,
                                           self.params.uncovered_cost)
                return float(total / n / self.h_target), coverage
            if self.frozen is not None:
                n = joint.sum()
                return float(np.sum(joint * self.frozen) / n / self.h_target), coverage
            if self.prior is not None:
                return float(_likelihood(joint, self.prior, self.params.prior_weight,
                                         self.h_target)), coverage
            return float(_likelihood(joint, _NO_PRIOR, 0.0, self.h_target)), coverage
        if self.costs is not None:
            total, n_valid, n_scene, n_covered = _cost_kernel(flat, self.target, self.start,
                                                              self.costs)
            total = total * _COST_UNIT
        else:
            total, n_valid, n_scene, n_covered = _loss_kernel(
                flat, self.target, self.table, self.start, self.dist, self.banded)
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
