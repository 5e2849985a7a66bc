"""The paper's valid pixels and the mean cost over them: the one kernel of the colour losses
(colour.py, balanced.py) and of the likelihood's learned costs (likelihood.py).

Validity, as in the paper's CARLA set-up: the target must carry a usable class; a pixel where no
map point landed counts where the target is sky (a match) and is masked where it is not (such
holes come from map sparsity, not from a wrong pose), unless ``loss.uncovered_cost`` charges it.
The likelihood's histogram (likelihood.py) counts those holes instead, as a rendered class of
their own: a different rule, kept in its own kernel.
"""

from __future__ import annotations

import numba

from semcal_ros.engine.labels import INVALID, SKY
from semcal_ros.engine.loss.params import LossParams

#: what :func:`cost_sum` charges a pixel: ``table[rendered, label]``; the precomputed
#: ``costs[rendered, pixel]`` (uint16 in ``unit``s, summed as integers); or the expected
#: ``table[rendered, k]`` under the pixel's ``probabilities[pixel, k]``
TABLE, PIXEL_COSTS, EXPECTED = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def cost_sum(rendered, target, start, table, empty, dist, banded, costs, probabilities, mode,
             unit):
    """(total cost, valid pixels, the target's map-class pixels, those a point covers) from
    pixel ``start`` on. ``empty`` is the row of ``table`` for nothing drawn where the labels
    have sky. A match costs 0 under ``TABLE``. With ``banded`` a rendered class's cost is
    weighted by its distance share in the labels (``dist[class, pixel]``, 255 = the band or
    farther; rows beyond ``dist``'s are not weighted)."""
    total = 0.0
    counts = 0
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
            r = empty
        n_valid += 1
        if mode == PIXEL_COSTS:
            counts += costs[r, p]
            continue
        if mode == EXPECTED:
            c = 0.0
            for k in range(probabilities.shape[1]):
                c += probabilities[p, k] * table[r, k]
        elif r == t:
            continue
        else:
            c = table[r, t]
        if banded and r < dist.shape[0]:
            c = c * dist[r, p] * (1.0 / 255.0)
        total += c
    return total + counts * unit, n_valid, n_scene, n_covered


def mean_cost(sums: tuple[float, int, int, int], params: LossParams, scale: float = 1.0
              ) -> tuple[float, float, bool]:
    """(loss, coverage, judged) from :func:`cost_sum`'s sums: the mean cost over the valid
    pixels, ``uncovered_cost`` charged for every map-class pixel no point covers, divided by
    ``scale``; ``degenerate_loss`` and judged False for a view that shows (almost) none of the
    map."""
    total, n_valid, n_scene, n_covered = sums
    coverage = n_covered / n_scene if n_scene else 0.0
    if params.uncovered_cost > 0:
        n_valid += n_scene - n_covered
        total += params.uncovered_cost * (n_scene - n_covered)
    if n_valid == 0 or coverage < params.min_coverage:
        return params.degenerate_loss, coverage, False
    return total / n_valid / scale, coverage, True


__all__ = ["EXPECTED", "PIXEL_COSTS", "TABLE", "cost_sum", "mean_cost"]
