"""The cues beside the labels (engine/cues.py): the numba kernels equal their numpy definitions,
the depth-edge term is lowest where the image's edges are the map's outlines, and a cue is
part of every loss the problem gives (search, evaluate, the quality report's path) when on and
costs nothing when off."""

from dataclasses import replace

import numpy as np
import pytest

from semcal_ros.engine.cues import (
    CuedLoss, CueParams, edge_terms, edge_terms_reference, image_edges,
    inverse_distance_transform, inverse_distance_transform_reference,
)
from semcal_ros.engine.loss import LabelLoss
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.render import fast, make_view, prepare_map
from semcal_ros.engine.render.view import EMPTY_KEY
from semcal_tools.synthetic import GROUND_TRUTH, camera

WEIGHT = 0.5


def _shifted(pose: Pose, axis: int, step: float) -> Pose:
    v = pose.vector()
    v[axis] += step
    return Pose.from_vector(v)


@pytest.fixture(scope="module")
def keys_at_truth(world):
    pmap = prepare_map(world, center=GROUND_TRUTH.translation)
    return fast.render_keys(pmap, make_view(camera(), GROUND_TRUTH, pmap.origin, 32.0, 8.0,
                                            depth_falloff=0.3))


@pytest.fixture(scope="module")
def outline_image(keys_at_truth):
    """A camera image whose only edges are the map's depth outlines at the truth (white lines
    on black): the picture the edge term should find."""
    _, den = edge_terms_reference(keys_at_truth, np.ones(keys_at_truth.shape, np.float32), 0, 0.5)
    assert den > 100  # the street has outlines (poles, facades against the far end)
    depth = (keys_at_truth >> 8).astype(np.float64)
    valid = keys_at_truth != EMPTY_KEY
    pad = np.pad(np.where(valid, depth, -np.inf), 1, constant_values=-np.inf)
    far = np.max(np.stack([pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]]), 0)
    edge = valid & (far > 1.5 * depth)
    return (edge * 255).astype(np.uint8)


def test_inverse_distance_transform_equals_its_definition():
    rng = np.random.default_rng(3)
    edges = np.where(rng.random((37, 53)) > 0.97, rng.random((37, 53)), 0.0).astype(np.float32)
    a = inverse_distance_transform(edges, 0.9, 0.333)
    b = inverse_distance_transform_reference(edges, 0.9, 0.333)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    # one edge pixel: the field falls by the decay per chessboard ring
    one = np.zeros((9, 9), np.float32)
    one[4, 4] = 1.0
    d = inverse_distance_transform(one, 0.5, 0.0)
    assert d[4, 4] == 1.0 and d[4, 6] == pytest.approx(0.25) and d[1, 7] == pytest.approx(0.125)


def test_edge_kernel_equals_its_definition(keys_at_truth):
    rng = np.random.default_rng(4)
    field = rng.random(keys_at_truth.shape).astype(np.float32)
    h, w = keys_at_truth.shape
    for start_row, jump, inset, kmax in ((0, 0.5, 0.0, 0), (h // 3, 0.2, 20.0, 5),
                                         (0, 1.0, 40.0, 3)):
        ref = edge_terms_reference(keys_at_truth, field, start_row, jump, inset, kmax)
        got = edge_terms(np.ascontiguousarray(keys_at_truth).ravel(), w, field.ravel(),
                         start_row * w, jump, inset, kmax)
        assert ref[1] > 0
        np.testing.assert_allclose(got, ref, rtol=1e-9)


def test_render_with_keys_is_render_and_render_keys_in_one(world):
    pmap = prepare_map(world, center=GROUND_TRUTH.translation)
    view = make_view(camera(), _shifted(GROUND_TRUTH, 0, 0.3), pmap.origin, 32.0, 8.0)
    labels, keys = fast.render_with_keys(pmap, view)
    np.testing.assert_array_equal(labels, fast.render(pmap, view))
    np.testing.assert_array_equal(keys, fast.render_keys(pmap, view))


def test_image_edges_are_scaled_to_one_and_blind_to_flat_images():
    flat = np.full((40, 60, 3), 128, np.uint8)
    assert not image_edges(flat).any()
    step = flat.copy()
    step[:, 30:] = 200
    e = image_edges(step)
    assert e.max() == pytest.approx(1.0) and e[:, :25].max() == 0.0 and e[:, 29:31].min() > 0.5


def test_cue_parameters_are_checked():
    with pytest.raises(ValueError, match="cues.edge_weight"):
        CueParams(edge_weight=-1.0)
    with pytest.raises(ValueError, match="cues.edge_decay"):
        CueParams(edge_decay=1.0)
    assert not CueParams().active  # off by default


def test_off_costs_nothing_and_on_needs_the_image(world, target):
    off = Problem(world, target, camera(), GROUND_TRUTH.translation)
    assert off.edges is None
    assert all(type(off.level(s).loss) is LabelLoss for s in range(len(off.stages)))
    params = replace(CalibrationParams(), cues=CueParams(edge_weight=WEIGHT))
    with pytest.raises(ValueError, match="needs the camera image"):
        Problem(world, target, camera(), GROUND_TRUTH.translation, params)
    with pytest.raises(ValueError, match="camera image is 10x10"):
        Problem(world, target, camera(), GROUND_TRUTH.translation, params,
                image=np.zeros((10, 10), np.uint8))


def test_edge_term_is_lowest_at_the_outlines_and_joins_every_loss(world, target, outline_image):
    # the image's lines are the render's own outlines (discs included): scored where found
    params = replace(CalibrationParams(), cues=CueParams(edge_weight=WEIGHT, edge_inset=0.0))
    problem = Problem(world, target, camera(), GROUND_TRUTH.translation, params,
                      image=outline_image)
    plain = Problem(None, target, camera(), GROUND_TRUTH.translation, prepared=problem.pmap)
    lv = problem.level(-1)
    assert isinstance(lv.loss, CuedLoss)

    def term(pose: Pose, stage: int = -1) -> float:
        problem.render(pose, stage)
        assert problem.last_render() is not None
        return problem.level(stage).loss.edge.term(problem.last_render()[1])

    at_truth = term(GROUND_TRUTH)
    assert at_truth < 0.35  # most depth edges sit on an image edge
    for axis, step in ((0, 0.3), (1, -0.3), (2, 0.3), (5, np.radians(1.0))):
        assert term(_shifted(GROUND_TRUTH, axis, step)) > at_truth + 0.03, (axis, step)
    # coarse levels sample the same field
    assert term(GROUND_TRUTH, 0) < term(_shifted(GROUND_TRUTH, 1, -0.5), 0)
    # the combined loss: label loss + weight x term, in loss(), evaluate() and the quality
    # report's path (level(-1).loss.evaluate of a render, also of a copy of it)
    pose = _shifted(GROUND_TRUTH, 0, 0.2)
    expected = plain.loss(pose) + WEIGHT * term(pose)
    assert problem.loss(pose) == pytest.approx(expected, rel=1e-12)
    assert problem.evaluate(pose).loss == pytest.approx(expected, rel=1e-12)
    rendered = problem.render(pose)
    assert lv.loss.evaluate(rendered)[0] == pytest.approx(expected, rel=1e-12)
    assert lv.loss(rendered.copy()) == pytest.approx(expected, rel=1e-12)
    # a label image that is none of the problem's renders: the label loss alone
    other = plain.render(_shifted(GROUND_TRUTH, 0, -0.4))
    assert lv.loss(other) == pytest.approx(plain.level(-1).loss(other), rel=1e-12)
    # masked problems keep the cue
    masked = problem.masked(np.zeros(target.shape, bool))
    assert masked.loss(pose) == pytest.approx(expected, rel=1e-12)
