"""The loss's parameters, one dataclass for every kind (``engine.loss`` in the config files)."""

from __future__ import annotations

from dataclasses import dataclass

#: The per-pixel costs, by parameter value, with the name tables print: the one list of them.
#: Each kind's code is a module of this package: colour.py (l2, huber), balanced.py,
#: likelihood.py (likelihood, mi).
LOSS_KINDS = {"l2": "L2", "huber": "Huber", "mi": "MI", "likelihood": "Likelihood",
              "balanced": "Balanced"}

N_CLASSES = 19  # aligned classes are Cityscapes trainIds 0..18


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
    # likelihood: EM's E step at each refinement stage's start (Dempster, Laird & Rubin 1977):
    # the confusion between map and label classes learned from the frame there and held through
    # the stage; how much the stage trusts it follows the labels' agreement (em_agreement)
    em: bool = True
    # the learned confusion's prior: this many pseudo-pixels per rendered class (full
    # resolution; a Dirichlet prior, so the frame's evidence outweighs it as it grows)
    em_prior_pixels: float = 100.0
    # the learned loss's share rises from 0 to 1 as the labels' agreement with the map at the
    # E step rises over this range (below: the likelihood re-estimated at every pose, tolerant of
    # a real segmenter's confusions; above: the learned costs alone, as sharp as L2 on clean
    # labels). Measured agreement: real frames 0.38-0.82, synthetic labels 0.93-0.99
    em_agreement: tuple[float, float] = (0.84, 0.90)
    # likelihood: in this share of the image's rows from the bottom, the pixels below the lowest
    # one the map draws in their column are left out of the histogram (the lidar's blind zone
    # near its mount is no evidence; likelihood.below_map_mask); 0 = counted as nothing drawn.
    # Bounded, so a view that draws the map high in the image cannot leave most of it out
    blind_rows: float = 0.0

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
        if not 0.0 < self.em_prior_pixels <= 1e6:
            raise ValueError(f"loss.em_prior_pixels must be in (0, 1e6], got "
                             f"{self.em_prior_pixels}")
        lo, hi = (float(v) for v in self.em_agreement)
        if not 0.0 <= lo < hi <= 1.0:
            raise ValueError(f"loss.em_agreement must be [low, high] with 0 <= low < high <= 1, "
                             f"got {list(self.em_agreement)}")
        if not 0.0 <= self.blind_rows <= 0.5:
            raise ValueError(f"loss.blind_rows must be in [0, 0.5], got {self.blind_rows}")
        if not 0.0 <= self.boundary_band_px <= 50.0:
            raise ValueError(f"loss.boundary_band_px must be in [0, 50], got "
                             f"{self.boundary_band_px}")
