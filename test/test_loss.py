"""Beta normalisation, masking and the class-pair table."""

import numpy as np
import pytest

from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, SKY, palette_array
from semcal_ros.engine.loss import LabelLoss, LossParams, loss_reference, pair_table

ROAD, BUILDING, VEG = CITYSCAPES_ID["road"], CITYSCAPES_ID["building"], CITYSCAPES_ID["vegetation"]
#: The paper's loss: every mismatch costs its full colour distance (the default adds a boundary band).
PAPER = LossParams(kind="l2", boundary_band_px=0.0)


def colour_l2(a, b):
    pal = palette_array().astype(float) / 255
    return float(np.sum((pal[a] - pal[b]) ** 2))


def test_table_is_colour_distance():
    t = pair_table("l2")
    assert t[ROAD, ROAD] == 0
    assert t[ROAD, BUILDING] == pytest.approx(colour_l2(ROAD, BUILDING))
    h = pair_table("huber", 0.3)
    assert h[ROAD, BUILDING] < t[ROAD, BUILDING]  # huber is linear beyond delta
    assert h[ROAD, ROAD] == 0


def test_mean_over_valid_pixels_and_masking():
    target = np.full((4, 10), ROAD, np.uint8)
    target[0] = SKY
    target[1, :5] = INVALID  # ignored in the target
    rendered = np.full((4, 10), ROAD, np.uint8)
    rendered[0] = INVALID  # nothing rendered over the sky: valid match, zero cost
    rendered[3, :2] = BUILDING  # two wrong pixels
    rendered[2, :4] = INVALID  # holes over non-sky: masked, not counted
    loss = LabelLoss(target, PAPER)
    value, coverage = loss.evaluate(rendered)
    n_valid = 40 - 5 - 4
    assert value == pytest.approx(2 * colour_l2(BUILDING, ROAD) / n_valid)
    assert coverage == pytest.approx((25 - 4) / 25)
    ref, ref_cov = loss_reference(rendered, target, loss.table, PAPER)
    assert ref == pytest.approx(value)
    assert ref_cov == pytest.approx(coverage)


def test_uncovered_cost_counts_holes_over_map_classes():
    target = np.full((4, 10), ROAD, np.uint8)
    target[0] = SKY
    rendered = np.full((4, 10), ROAD, np.uint8)
    rendered[0] = INVALID  # over the sky: a match either way
    rendered[3, :2] = BUILDING
    rendered[2, :4] = INVALID  # 4 holes over road: masked by the paper, costed here
    params = LossParams(kind="l2", uncovered_cost=0.5)
    value, coverage = LabelLoss(target, params).evaluate(rendered)
    assert value == pytest.approx((2 * colour_l2(BUILDING, ROAD) + 4 * 0.5) / 40)
    assert coverage == pytest.approx(26 / 30)
    ref, _ = loss_reference(rendered, target, LabelLoss(target, params).table, params)
    assert ref == pytest.approx(value)
    # a view that no longer shows the mismatching part wins under the paper's masked mean,
    # and loses once uncovered map classes cost something
    away = rendered.copy()
    away[3] = INVALID
    assert LabelLoss(target, PAPER)(away) < LabelLoss(target, PAPER)(rendered)
    assert LabelLoss(target, params)(away) > value
    with pytest.raises(ValueError, match="uncovered_cost"):
        LossParams(uncovered_cost=-1.0)


def test_beta_normalisation_does_not_reward_masking():
    # the same error rate over fewer valid pixels gives the same loss
    target = np.full((10, 10), ROAD, np.uint8)
    rendered = target.copy()
    rendered[:, 0] = BUILDING
    full = LabelLoss(target, PAPER)(rendered)
    holes = rendered.copy()
    holes[:5, 1:] = INVALID
    holes[:5, 0] = INVALID
    assert LabelLoss(target, PAPER)(holes) == pytest.approx(full)


def test_rendered_map_over_target_sky_costs():
    target = np.full((2, 2), SKY, np.uint8)
    target[1] = ROAD
    rendered = np.full((2, 2), ROAD, np.uint8)
    value = LabelLoss(target, PAPER)(rendered)
    assert value == pytest.approx(2 * colour_l2(ROAD, SKY) / 4)


def test_crop_top_and_degenerate_view():
    target = np.full((10, 4), ROAD, np.uint8)
    rendered = target.copy()
    rendered[:5] = BUILDING
    assert LabelLoss(target, LossParams(kind="l2", crop_top=0.5))(rendered) == 0.0
    empty = np.full_like(target, INVALID)
    p = LossParams(min_coverage=0.05, degenerate_loss=7.0)
    assert LabelLoss(target, p)(empty) == 7.0


def test_fast_matches_reference_on_random_images():
    rng = np.random.default_rng(3)
    classes = np.array([0, 1, 2, 5, 7, 8, 9, 10, INVALID], np.uint8)
    target = rng.choice(classes, (60, 80)).astype(np.uint8)
    rendered = rng.choice(classes, (60, 80)).astype(np.uint8)
    for kind in ("l2", "huber"):
        p = LossParams(kind=kind, crop_top=0.1, min_coverage=0.0)
        loss = LabelLoss(target, p)
        assert loss(rendered) == pytest.approx(loss_reference(rendered, target, loss.table, p)[0])


def test_bad_loss_kind():
    with pytest.raises(ValueError, match="loss.kind must be one of l2, huber"):
        LossParams(kind="l1")


def test_boundary_band_discounts_mismatches_near_the_class_and_matches_the_reference():
    target = np.full((20, 40), ROAD, np.uint8)
    target[:10, :20] = BUILDING
    target[:3] = SKY
    band = LossParams(kind="l2", boundary_band_px=4.0)
    # building drawn 2 px too far right: the wrong pixels lie within 2 px of the target's building
    shifted = target.copy()
    shifted[3:10, 20:22] = BUILDING
    # building drawn far from any building: full cost
    far = target.copy()
    far[15:17, 30:32] = BUILDING
    paper, banded = LabelLoss(target, PAPER), LabelLoss(target, band)
    assert banded(target) == 0.0
    assert banded(shifted) < 0.5 * paper(shifted)  # near the boundary: discounted
    assert banded(far) == pytest.approx(paper(far))  # 4+ px away: the full colour distance
    for rendered in (shifted, far):
        ref, _ = loss_reference(rendered, target, banded.table, band)
        assert ref == pytest.approx(banded(rendered))
    # the band is in full-resolution pixels: at scale 2 it is 2 px of the downsampled image
    assert LabelLoss(target[::2, ::2], band, scale=2).band_px == 2.0
    with pytest.raises(ValueError, match="loss.boundary_band_px"):
        LossParams(boundary_band_px=-1.0)


def test_label_outliers_keep_wide_disagreement_and_drop_thin_bands():
    from semcal_ros.engine.loss import label_outliers

    target = np.full((60, 80), ROAD, np.uint8)
    target[:30] = BUILDING
    rendered = target.copy()
    rendered[30:32] = BUILDING  # a 2 px band along the boundary: what a small pose error draws
    target[40:55, 10:30] = VEG  # a 15 x 20 px blob of a wrong class in the labels
    out = label_outliers(rendered, target, width_px=7)
    assert out[40:55, 10:30].all()  # the blob is taken for a label error
    assert not out[28:34].any()  # the thin band is not
    with pytest.raises(ValueError, match="loss.outlier_width_px"):
        LossParams(outlier_width_px=-2.0)


# -- issue 18: losses for real segmenters ---------------------------------------------------------

MI = LossParams(kind="mi", min_coverage=0.0)


def _street(h=40, w=60):
    """Sky, building on the left, vegetation on the right, road below."""
    target = np.full((h, w), ROAD, np.uint8)
    target[: h // 4] = SKY
    target[h // 4: h // 2, : w // 2] = BUILDING
    target[h // 4: h // 2, w // 2:] = VEG
    return target


def test_mutual_information_tolerates_a_consistent_confusion():
    target = _street()
    # the network called every vegetation pixel building: a consistent confusion
    confused = np.where(target == VEG, BUILDING, target).astype(np.uint8)
    rendered = target.copy()  # the map at the truth
    shifted = np.roll(target, 3, axis=0)  # the map 3 px low
    mi, l2 = LabelLoss(confused, MI), LabelLoss(confused, PAPER)
    # MI: the truth's render still explains the labels better than a shifted one
    assert mi(rendered) < mi(shifted)
    # a renaming of classes carries the same information: loss 0 at a perfect render
    assert LabelLoss(target, MI)(np.where(target == ROAD, VEG, np.where(
        target == VEG, ROAD, target)).astype(np.uint8)) == pytest.approx(0.0, abs=1e-12)
    assert mi(rendered) == pytest.approx(0.0, abs=1e-12) and l2(rendered) > 0.01  # L2 charges them


def test_mutual_information_counts_nothing_rendered_and_matches_the_reference():
    target = _street()
    rendered = target.copy()
    rendered[target == SKY] = INVALID  # nothing is rendered over the sky
    truth = rendered.copy()
    rendered[30:, 40:] = BUILDING  # a wrong region
    away = rendered.copy()
    away[30:, 40:] = INVALID  # a view that no longer shows it
    loss = LabelLoss(target, MI)
    # hiding the mismatch is not free: "nothing rendered" is a class that says little
    assert loss(truth) == 0.0
    assert loss(away) > 0.0
    rng = np.random.default_rng(5)
    classes = np.array([0, 2, 8, 9, 10, INVALID], np.uint8)
    t = rng.choice(classes, (50, 70)).astype(np.uint8)
    r = rng.choice(classes, (50, 70)).astype(np.uint8)
    p = LossParams(kind="mi", crop_top=0.2, min_coverage=0.0)
    value, cov = LabelLoss(t, p).evaluate(r)
    ref, ref_cov = loss_reference(r, t, pair_table("l2"), p)
    assert value == pytest.approx(ref, rel=1e-9)
    assert cov == pytest.approx(ref_cov)
    assert 0.0 < value <= 1.0
    empty = np.full_like(t, INVALID)
    assert LabelLoss(t, LossParams(kind="mi", min_coverage=0.05))(empty) == 10.0


def test_class_probabilities_give_the_expected_cost():
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.engine.loss import N_CLASSES, aligned_probabilities

    target = _street()
    rendered = np.roll(target, 2, axis=0)
    one_hot = np.zeros(target.shape + (N_CLASSES,), np.float32)
    ok = target < N_CLASSES
    one_hot[ok, target[ok]] = 1.0
    lut = LabelMapping().image_lut()
    for band in (0.0, 4.0):
        p = LossParams(kind="l2", boundary_band_px=band)
        # certain probabilities = the argmax loss (up to the uint16 cost quantisation)
        sure = LabelLoss(target, p, probabilities=aligned_probabilities(one_hot, lut, target))
        assert sure(rendered) == pytest.approx(LabelLoss(target, p)(rendered), abs=1e-4)
    # a pixel the network was unsure of costs less when the render shows its second choice
    unsure = one_hot.copy()
    unsure[target == VEG] = 0.0
    unsure[target == VEG, VEG] = 0.6
    unsure[target == VEG, BUILDING] = 0.4
    q = aligned_probabilities(unsure, lut, target)
    as_building = np.where(target == VEG, BUILDING, target).astype(np.uint8)
    soft = LabelLoss(target, PAPER, probabilities=q)
    assert soft(as_building) == pytest.approx(0.6 * LabelLoss(target, PAPER)(as_building),
                                              rel=1e-3)
    ref, _ = loss_reference(as_building, target, soft.table, PAPER, probabilities=q)
    assert ref == pytest.approx(soft(as_building), rel=1e-9)
    # MI fills its histogram with them
    mi_soft = LabelLoss(target, MI, probabilities=q)
    ref, _ = loss_reference(as_building, target, soft.table, MI, probabilities=q)
    assert mi_soft(as_building) == pytest.approx(ref, rel=1e-9)


def test_probabilities_file_errors_are_one_line(tmp_path):
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.engine.loss import aligned_probabilities, read_probabilities

    bad = tmp_path / "p.npz"
    np.savez(bad, other=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="no 'probabilities' array"):
        read_probabilities(bad)
    np.savez(bad, probabilities=np.zeros((4, 5, 3), np.float16))
    with pytest.raises(ValueError, match=r"must be \(H, W, 19\)"):
        read_probabilities(bad)
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        read_probabilities(tmp_path / "junk.npz")
    with pytest.raises(ValueError, match="probabilities must be"):
        aligned_probabilities(np.zeros((3, 3, 19)), LabelMapping().image_lut(),
                              np.zeros((4, 4), np.uint8))
