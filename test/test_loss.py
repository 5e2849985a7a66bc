"""Beta normalisation, masking and the class-pair table."""

import numpy as np
import pytest

from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, SKY, palette_array
from semcal_ros.engine.loss import LabelLoss, LossParams, loss_reference, pair_table

ROAD, BUILDING, VEG = CITYSCAPES_ID["road"], CITYSCAPES_ID["building"], CITYSCAPES_ID["vegetation"]
#: The paper's loss: every mismatch costs its full colour distance (the default adds a boundary band).
PAPER = LossParams(boundary_band_px=0.0)


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
    params = LossParams(uncovered_cost=0.5)
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
    assert LabelLoss(target, LossParams(crop_top=0.5))(rendered) == 0.0
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
    band = LossParams(boundary_band_px=4.0)
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
