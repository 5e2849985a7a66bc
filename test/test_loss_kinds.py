"""The losses for real labels: the likelihood under a confusion matrix (tolerates a consistent
confusion, cannot be won by swapping classes), its EM form, and the class-balanced mismatch."""

from dataclasses import replace

import numpy as np
import pytest

from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, SKY
from semcal_ros.engine.loss import (
    LabelLoss, LossParams, balanced_table, confusion_prior, likelihood_share, loss_reference,
    pair_table,
)

ROAD, BUILDING, VEG, CAR = (CITYSCAPES_ID[c] for c in ("road", "building", "vegetation", "car"))


def _street(h: int = 90, w: int = 120) -> np.ndarray:
    """Labels of a street: sky, building band, vegetation, road, a car."""
    t = np.full((h, w), SKY, np.uint8)
    t[20:45] = BUILDING
    t[45:55, : w // 2] = VEG
    t[45:55, w // 2:] = BUILDING
    t[55:] = ROAD
    t[60:75, 30:50] = CAR
    return t


def _render(labels: np.ndarray, shift: int = 0) -> np.ndarray:
    """The map drawn with a vertical offset (a pitch error); nothing drawn over sky."""
    r = np.roll(labels, shift, axis=0).copy()
    r[r == SKY] = INVALID
    return r


@pytest.mark.parametrize("kind", ["likelihood", "balanced", "mi"])
def test_the_kernel_equals_the_reference(kind):
    rng = np.random.default_rng(1)
    t = _street()
    r = _render(t, 2)
    noise = rng.random(t.shape) < 0.1
    r[noise] = rng.choice([ROAD, BUILDING, VEG, INVALID], int(noise.sum()))
    params = LossParams(kind=kind)
    table = balanced_table(t) if kind == "balanced" else pair_table(kind)
    got = LabelLoss(t, params).evaluate(r)
    ref = loss_reference(r, t, table, params)
    assert got[0] == pytest.approx(ref[0], rel=1e-9) and got[1] == pytest.approx(ref[1])


@pytest.mark.parametrize("kind", ["likelihood", "mi"])
@pytest.mark.parametrize("soft", [False, True])
def test_the_kernel_equals_the_reference_with_the_blind_zone_left_out(kind, soft):
    rng = np.random.default_rng(2)
    t = _street()
    r = _render(t, 2)
    noise = rng.random(t.shape) < 0.1
    r[noise] = rng.choice([ROAD, BUILDING, VEG, INVALID], int(noise.sum()))
    r[70:, :] = INVALID  # the lidar's blind zone ...
    r[:, 100:] = INVALID  # ... and columns it draws nothing in
    probs = None
    if soft:
        probs = rng.random(t.shape + (19,)).astype(np.float32)
        probs /= probs.sum(axis=-1, keepdims=True)
    for crop in (0.0, 0.2):
        params = LossParams(kind=kind, blind_rows=0.4, crop_top=crop)
        got = LabelLoss(t, params, probabilities=probs).evaluate(r)
        ref = loss_reference(r, t, None, params, probabilities=probs)
        assert got[0] == pytest.approx(ref[0], rel=1e-9) and got[1] == pytest.approx(ref[1])
        counted = LabelLoss(t, replace(params, blind_rows=0.0),
                            probabilities=probs).evaluate(r)
        assert got[1] == counted[1]  # the coverage still counts every scene pixel
        assert got[0] != pytest.approx(counted[0])


def test_below_map_mask_marks_what_lies_under_the_lowest_drawn_pixel_of_each_column():
    from semcal_ros.engine.loss.likelihood import below_map_mask

    r = np.full((6, 3), INVALID, np.uint8)
    r[1, 0] = ROAD  # column 0: drawn down to row 1
    r[[2, 4], 1] = ROAD  # column 1: down to row 4 (a hole at row 3 stays counted)
    mask = below_map_mask(r)  # column 2: nothing drawn, all of it below the map
    np.testing.assert_array_equal(mask[:, 0], [0, 0, 1, 1, 1, 1])
    np.testing.assert_array_equal(mask[:, 1], [0, 0, 0, 0, 0, 1])
    assert mask[:, 2].all()
    half = below_map_mask(r, 0.5)  # only the lowest 3 of 6 rows may be left out
    np.testing.assert_array_equal(half[:, 0], [0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(half[:, 2], [0, 0, 0, 1, 1, 1])


def test_a_view_from_too_high_wins_on_the_blind_zone_unless_it_is_left_out():
    """The map of a top-mounted lidar stops short of the camera's nearest road (no beam reaches
    it). Counted as nothing drawn, that road rewards a view that stretches the map's ground over
    it, though the building then lies on the sky and the road on the building; left out, the
    truth wins."""
    h, w = 60, 40
    t = np.full((h, w), SKY, np.uint8)
    t[10:30] = BUILDING
    t[30:] = ROAD
    truth = np.full((h, w), INVALID, np.uint8)
    truth[10:30] = BUILDING
    truth[30:45] = ROAD  # rows 45-59: the blind zone
    high = np.full((h, w), INVALID, np.uint8)
    high[8:28] = BUILDING
    high[28:] = ROAD
    counted = LabelLoss(t, LossParams(em=False, boundary_band_px=0.0))
    left_out = LabelLoss(t, LossParams(em=False, boundary_band_px=0.0, blind_rows=0.3))
    assert counted(high) < counted(truth)
    assert left_out(truth) < left_out(high)


def test_swapped_classes_cost_under_the_likelihood_but_not_under_mi():
    """MI sees only how informative the rendered class is of the label: drawing road where the
    labels say building and building where they say road is as good as the truth. The
    likelihood's prior makes the swap cost; the balanced mismatch too."""
    t = _street()
    truth = _render(t)
    swapped = truth.copy()
    swapped[truth == ROAD], swapped[truth == BUILDING] = BUILDING, ROAD
    mi = LabelLoss(t, LossParams(kind="mi"))
    assert mi(swapped) == pytest.approx(mi(truth), abs=1e-12)
    for kind in ("likelihood", "balanced"):
        loss = LabelLoss(t, LossParams(kind=kind))
        assert loss(swapped) > loss(truth) + 0.1, kind


def test_a_consistent_confusion_costs_the_likelihood_little_and_the_truth_still_wins():
    """The point labeller calls a facade vegetation: at the truth every such pixel disagrees
    in class, but consistently. The likelihood stays lowest at the truth: a view shifted by a
    few rows, which puts other classes on the facade, is worse."""
    t = _street()
    truth = _render(t)
    confused = truth.copy()
    confused[45:55, 60:] = VEG  # the map's facade labelled vegetation
    lik = LabelLoss(t, LossParams(kind="likelihood"))
    for rows in (-4, -2, 2, 4):
        assert lik(confused) < lik(np.roll(confused, rows, axis=0)), rows


def test_the_prior_weight_spans_mi_and_a_fixed_identity():
    joint = np.zeros((20, 19))
    joint[ROAD, ROAD], joint[ROAD, BUILDING] = 80, 20
    joint[BUILDING, BUILDING], joint[19, SKY] = 90, 50
    prior = confusion_prior(0.3)
    assert np.allclose(prior.sum(axis=1), 1.0)
    from semcal_ros.engine.loss import conditional_entropy_share

    assert likelihood_share(joint, prior, 0.0) == pytest.approx(conditional_entropy_share(joint))
    assert likelihood_share(joint, prior, 1.0) > likelihood_share(joint, prior, 0.0)


def test_the_e_step_trusts_the_learned_costs_as_far_as_the_labels_agree():
    """Clean labels (agreement 1 at the E step) get the learned costs alone: 0 at the truth.
    Labels that agree on less than ``em_agreement``'s low end keep the likelihood re-estimated
    at each pose, unchanged; in between, the loss is the blend. Thawed: re-estimated again."""
    t = _street()
    truth, off = _render(t), _render(t, 3)
    params = LossParams(kind="likelihood", em=True)
    plain = LabelLoss(t, replace(params, em=False))
    loss = LabelLoss(t, params)
    loss.freeze(truth)
    assert loss.cost.share == 1.0 and loss(truth) == 0.0 and loss(off) > 0.0
    loss.thaw()
    assert loss(off) == pytest.approx(plain(off), rel=1e-12)
    poor = truth.copy()  # a real segmenter's agreement: 30 % of what is drawn disagrees
    rng = np.random.default_rng(0)
    drawn = np.nonzero(poor.ravel() != INVALID)[0]
    poor.ravel()[rng.choice(drawn, int(0.3 * drawn.size), replace=False)] = VEG
    loss.freeze(poor)
    assert loss.cost.share == 0.0 and loss(off) == pytest.approx(plain(off), rel=1e-12)
    middle = truth.copy()  # 13 % disagree: agreement 0.87, halfway through the range
    middle.ravel()[rng.choice(drawn, int(0.13 * drawn.size), replace=False)] = CAR
    loss.freeze(middle)
    assert 0.3 < loss.cost.share < 0.7
    sharp = LabelLoss(t, replace(params, em_agreement=(0.0, 0.01)))
    sharp.freeze(middle)  # the same learned costs, trusted in full
    share = loss.cost.share
    assert loss(off) == pytest.approx(share * sharp(off) + (1 - share) * plain(off), rel=1e-12)


def test_loss_parameters_are_checked():
    with pytest.raises(ValueError, match="prior_weight"):
        LossParams(kind="likelihood", prior_weight=-1.0)
    with pytest.raises(ValueError, match="confusion_weight"):
        replace(LossParams(), confusion_weight=2.0)
    with pytest.raises(ValueError, match="em_prior_pixels"):
        LossParams(em_prior_pixels=0.0)
    with pytest.raises(ValueError, match="em_agreement"):
        LossParams(em_agreement=(0.9, 0.8))
    with pytest.raises(ValueError, match="blind_rows"):
        LossParams(blind_rows=0.8)


def test_the_default_is_the_likelihood_and_the_paper_loss_file_selects_l2():
    from pathlib import Path

    from semcal_ros.engine.params import CalibrationParams

    assert CalibrationParams().loss.kind == "likelihood"
    path = Path(__file__).resolve().parents[1] / "config" / "paper_loss.yaml"
    params = CalibrationParams.from_file(str(path))
    assert params.loss.kind == "l2" and params.loss.boundary_band_px == 4.0
    assert params.search == CalibrationParams().search  # nothing else changed


def _learned_reference(rendered, target, costs, dist_band, uncovered=0.0):
    """The learned EM loss in numpy: per pixel the learned cost, banded, L2's validity."""
    from semcal_ros.engine.loss import class_distances

    r = rendered.ravel().astype(int)
    t = target.ravel().astype(int)
    dist = class_distances(target, dist_band) if dist_band > 0 else None
    total, n = 0.0, 0
    for p in range(t.size):
        if t[p] == INVALID:
            continue
        rp = r[p]
        if rp == INVALID:
            if t[p] != SKY:
                if uncovered > 0:
                    total, n = total + uncovered, n + 1
                continue
            rp = SKY
        n += 1
        if rp != t[p]:
            c = costs[rp, t[p]]
            total += c * (dist[rp, p] / 255.0 if dist is not None else 1.0)
    return total, n


def test_learned_costs_are_near_uniform_on_clean_labels_and_cheap_for_a_real_confusion():
    """The E step learns the frame's own confusion: on clean labels every mismatch costs about
    the same (and a match 0); a confusion the frame shows consistently (the map's facade as
    vegetation, 40 % of the building rows) costs little while a swap stays dear."""
    from semcal_ros.engine.loss import learned_costs

    prior = confusion_prior(0.3)
    clean = np.zeros((20, 19))
    for c, n in ((ROAD, 50000), (BUILDING, 30000), (VEG, 20000), (CAR, 5000)):
        clean[c, c] = n
    clean[ROAD, BUILDING] = clean[BUILDING, ROAD] = 50  # a few boundary pixels
    clean[19, SKY] = 40000
    costs = learned_costs(clean, prior, 100.0)
    assert np.all(np.diag(costs[:19, :19]) == 0) and costs[19, SKY] == 0
    # a usual confusion (building/vegetation in the prior) the frame does not show costs about
    # as much as any other mismatch: the prior does not cap what agreement earns
    assert costs[BUILDING, VEG] > 4.5 and costs[ROAD, CAR] > 4.5
    real = clean.copy()
    real[BUILDING, BUILDING], real[BUILDING, VEG] = 18000, 12000
    costs = learned_costs(real, prior, 100.0)
    assert costs[BUILDING, VEG] < 1.5  # log(C[veg, veg] / C[building, veg]) ~ log(1 / 0.4)
    assert costs[ROAD, BUILDING] > 4.0 and costs[BUILDING, ROAD] > 4.0  # swaps stay dear


def test_the_learned_prior_weighs_less_as_the_evidence_grows():
    """A Dirichlet prior of fixed pixels: the same shares from ten times the pixels move C
    towards the frame's own (a usual confusion the frame never shows grows dearer)."""
    from semcal_ros.engine.loss import learned_costs

    prior = confusion_prior(0.3)
    small = np.zeros((20, 19))
    small[BUILDING, BUILDING], small[VEG, VEG], small[19, SKY] = 300, 300, 300
    few = learned_costs(small, prior, 100.0)[BUILDING, VEG]
    many = learned_costs(small * 10, prior, 100.0)[BUILDING, VEG]
    assert many > few + 1.0


def test_the_learned_em_loss_is_zero_at_a_clean_truth_grows_with_the_error_and_matches_numpy():
    """Held at the truth of clean labels, the learned loss is 0 there and grows with a pitch
    error (smoothly near the truth: the boundary band), and its kernel equals the numpy
    reference; thawed, it is the likelihood re-estimated at each pose again."""
    from semcal_ros.engine.loss import learned_costs

    t = _street()
    truth = _render(t)
    params = LossParams(kind="likelihood", em=True, em_prior_pixels=100.0)
    loss = LabelLoss(t, params)
    free = loss(_render(t, 2))
    loss.freeze(truth)
    assert loss(truth) == 0.0
    values = [loss(_render(t, k)) for k in (1, 2, 3, 6)]
    assert all(b > a for a, b in zip([0.0] + values, values)), values
    assert values[0] < 0.5 * values[1]  # within the band a 1-row error costs little
    joint = np.zeros((20, 19))
    flat, tt = truth.ravel(), t.ravel()
    for r, c in zip(flat, tt):
        joint[19 if r == INVALID else r, c] += 1
    costs = learned_costs(joint, confusion_prior(params.confusion_weight), 100.0)
    off = _render(t, 3)
    total, n = _learned_reference(off, t, costs, params.boundary_band_px)
    assert loss(off) == pytest.approx(total / n / loss.cost.h_target, rel=1e-9)
    loss.thaw()
    assert loss(_render(t, 2)) == pytest.approx(free)


def test_held_at_a_consistent_confusion_the_truth_still_wins():
    """Held where the map's facade is labelled vegetation, the truth (with that confusion)
    beats views a few rows off, which put other classes on the facade."""
    t = _street()
    confused = _render(t)
    confused[45:55, 60:] = VEG
    loss = LabelLoss(t, LossParams(kind="likelihood", em=True, em_prior_pixels=100.0))
    loss.freeze(confused)
    for rows in (-4, -2, 2, 4):
        assert loss(confused) < loss(np.roll(confused, rows, axis=0)), rows


def test_the_learned_em_loss_of_a_one_hot_softmax_equals_the_argmax_one():
    """A soft target whose softmax is certain costs what its argmax labels cost (band and
    masking alike); an unsure pixel costs its expected cost."""
    t = _street()
    q = np.zeros(t.shape + (19,), np.float32)
    q[np.arange(t.shape[0])[:, None], np.arange(t.shape[1])[None, :], t] = 1.0
    params = LossParams(kind="likelihood", em=True, em_prior_pixels=100.0)
    hard, soft = LabelLoss(t, params), LabelLoss(t, params, probabilities=q)
    truth = _render(t)
    hard.freeze(truth)
    soft.freeze(truth)
    off = _render(t, 2)
    assert soft(off) == pytest.approx(hard(off), rel=1e-9) and hard(off) > 0
    q[50:52, :, ROAD], q[50:52, :, VEG] = 0.5, 0.5  # unsure rows at the vegetation's lower edge
    unsure = LabelLoss(t, params, probabilities=q)
    unsure.freeze(truth)
    assert unsure(off) != pytest.approx(soft(off), rel=1e-6)
