"""The intensity cue (engine/cues.py): lidar intensity against image grey level by the normalised
information distance. Its NID is 0 for identical images and near 1 for independent ones, its
kernels equal their numpy definitions, the renderer draws the winning point's intensity in the
same pass as the labels, the term is lowest at the truth on a synthetic street whose camera image
is its intensity, and maps carry intensity from the scans to map.ply and back (files without it
still load; the cue then says in one line that it cannot run)."""

from dataclasses import replace

import numpy as np
import pytest
from plyfile import PlyData

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.cues import (
    CuedLoss, CueParams, code_bins, grey_bins, intensity_histogram, nid_of_histogram,
    nid_reference,
)
from semcal_ros.engine.loss import LabelLoss
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.render import fast, make_view, prepare_map, reference
from semcal_ros.engine.render.prepare import NO_INTENSITY, intensity_codes
from semcal_ros.io.ply import read_ply, write_ply
from semcal_ros.mapping import MapBuildParams, ScanInput, build_map
from semcal_ros.mapping.filters import voxel_downsample
from semcal_tools.synthetic import GROUND_TRUTH, camera

WEIGHT = 1.0


def _shifted(pose: Pose, axis: int, step: float) -> Pose:
    v = pose.vector()
    v[axis] += step
    return Pose.from_vector(v)


@pytest.fixture(scope="module")
def bright_world(world):
    """The synthetic street with an intensity per point that varies over each surface (stripes
    of 0.7 m along x and z, a different offset per class): a pattern that shifts with the pose."""
    xyz = world.xyz
    stripes = (np.floor(xyz[:, 0] / 0.7) + np.floor(xyz[:, 2] / 0.7)) % 4
    intensity = (stripes * 40.0 + world.label.astype(np.float64) % 7 * 5.0).astype(np.float32)
    return LabelledCloud(world.xyz, world.label, {"intensity": intensity})


@pytest.fixture(scope="module")
def intensity_image(bright_world):
    """The camera image of the street at the truth: its rendered intensity codes as grey levels,
    uniform noise where the map renders nothing (the sky)."""
    pmap = prepare_map(bright_world, center=GROUND_TRUTH.translation)
    problem = Problem(None, np.zeros((600, 960), np.uint8), camera(), GROUND_TRUTH.translation,
                      prepared=pmap)
    view = problem.level(-1).setup.view(GROUND_TRUTH)
    _, _, values = fast.render_with_values(pmap, view, pmap.intensity)
    noise = np.random.default_rng(5).integers(0, 255, values.shape).astype(np.uint8)
    return np.where(values == NO_INTENSITY, noise, values).astype(np.uint8)


def test_nid_is_zero_for_identical_and_near_one_for_independent_images():
    rng = np.random.default_rng(0)
    x = rng.integers(0, 10, 100_000)
    assert nid_reference(x, x, 10) == pytest.approx(0.0, abs=1e-12)
    assert nid_reference(x, (x * 7 + 3) % 10, 10) == pytest.approx(0.0, abs=1e-12)  # relabelled
    y = rng.integers(0, 10, 100_000)
    assert nid_reference(x, y, 10) > 0.99
    # half the pixels agree: in between
    z = np.where(rng.random(100_000) < 0.5, x, y)
    assert 0.3 < nid_reference(x, z, 10) < 0.9
    # the kernel on the joint histogram is the same number
    for a, b in ((x, x), (x, y), (x, z)):
        hist = np.histogram2d(a, b, bins=10, range=[[0, 10], [0, 10]])[0].astype(np.int64)
        assert nid_of_histogram(hist) == pytest.approx(nid_reference(a, b, 10), abs=1e-12)
    assert nid_of_histogram(np.zeros((10, 10), np.int64)) == 1.0  # nothing: no information


def test_histogram_kernel_equals_its_definition():
    rng = np.random.default_rng(1)
    h, w, bins = 41, 57, 10
    values = rng.integers(0, 256, (h, w)).astype(np.uint8)  # 255: no intensity
    grey = rng.integers(0, bins, (h, w)).astype(np.uint8)
    start_row = 7
    lut = code_bins(bins)
    got = intensity_histogram(values.ravel(), grey.ravel(), start_row * w, lut, bins)
    ok = values[start_row:] != 255
    expected = np.histogram2d(lut[values[start_row:][ok]], grey[start_row:][ok], bins=bins,
                              range=[[0, bins], [0, bins]])[0]
    np.testing.assert_array_equal(got, expected)
    assert lut[0] == 0 and lut[254] == bins - 1 and lut[255] == 255
    assert np.all(np.bincount(lut[:255], minlength=bins) >= 25)  # codes spread over every bin


def test_intensity_codes_are_ranks_blind_to_the_scale():
    rng = np.random.default_rng(2)
    kitti = rng.random(5000).astype(np.float32)  # 0-1 reflectance
    kitti[:10] = np.nan
    pjlab = np.float32(255.0) * kitti ** 2  # another scale, monotone
    np.testing.assert_array_equal(intensity_codes(kitti), intensity_codes(pjlab))
    codes = intensity_codes(kitti)
    assert np.all(codes[:10] == NO_INTENSITY) and codes[10:].max() <= 254
    assert np.all(np.bincount(codes[10:], minlength=255)[:255] <= 5000 // 255 + 2)  # equal bins
    # grey bins: equally filled whatever the brightness
    dark = (rng.random((60, 80)) * 40).astype(np.uint8)
    counts = np.bincount(grey_bins(dark, 10, dark.shape).ravel(), minlength=10)
    assert counts.min() > 0.05 * dark.size


def test_render_with_values_equals_the_reference(bright_world):
    pmap = prepare_map(bright_world, center=GROUND_TRUTH.translation)
    view = make_view(camera(480, 300), _shifted(GROUND_TRUTH, 0, 0.3), pmap.origin, 16.0, 4.0,
                     depth_falloff=0.3, core_fraction=0.7, lod_radius=0.75)
    keys_ref, values_ref = reference.render_values(pmap, view, pmap.intensity)
    labels, keys, values = fast.render_with_values(pmap, view, pmap.intensity, n_threads=1)
    np.testing.assert_array_equal(keys, keys_ref)
    np.testing.assert_array_equal(values, values_ref)
    np.testing.assert_array_equal(labels, reference.keys_to_labels(keys_ref))
    assert (values != NO_INTENSITY).mean() > 0.3  # the street covers much of the view
    # two threads: the same labels and keys; values differ only where equal keys tie
    labels2, keys2, values2 = fast.render_with_values(pmap, view, pmap.intensity, n_threads=2)
    np.testing.assert_array_equal(labels2, labels)
    np.testing.assert_array_equal(keys2, keys)
    assert (values2 != values).mean() < 1e-3
    # the plain render is unchanged by the values' path
    np.testing.assert_array_equal(fast.render(pmap, view), labels)
    with pytest.raises(ValueError, match="values for"):
        fast.render_with_values(pmap, view, pmap.intensity[:-1])


def test_nid_term_is_lowest_at_the_truth_and_joins_every_loss(bright_world, target,
                                                              intensity_image):
    params = replace(CalibrationParams(), cues=CueParams(intensity_weight=WEIGHT))
    problem = Problem(bright_world, target, camera(), GROUND_TRUTH.translation, params,
                      image=intensity_image)
    plain = Problem(None, target, camera(), GROUND_TRUTH.translation, prepared=problem.pmap)
    lv = problem.level(-1)
    assert isinstance(lv.loss, CuedLoss) and lv.loss.edge is None

    def term(pose: Pose, stage: int = -1) -> float:
        problem.render(pose, stage)
        assert problem.last_render() is not None and problem.last_render()[2] is not None
        return problem.level(stage).loss.intensity.term(problem.last_render()[2])

    at_truth = term(GROUND_TRUTH)
    # the image is the map's intensity (binned by its own quantiles, so not bin for bin)
    assert at_truth < 0.15
    for axis, step in ((0, 0.3), (1, -0.3), (2, 0.3), (4, np.radians(0.5)),
                       (5, np.radians(-0.5))):
        assert term(_shifted(GROUND_TRUTH, axis, step)) > at_truth + 0.3, (axis, step)
    assert term(GROUND_TRUTH, 0) < term(_shifted(GROUND_TRUTH, 1, -0.5), 0)  # coarse levels too
    pose = _shifted(GROUND_TRUTH, 0, 0.2)
    expected = plain.loss(pose) + WEIGHT * term(pose)
    assert problem.loss(pose) == pytest.approx(expected, rel=1e-12)
    assert problem.evaluate(pose).loss == pytest.approx(expected, rel=1e-12)
    assert lv.loss(problem.render(pose).copy()) == pytest.approx(expected, rel=1e-12)
    masked = problem.masked(np.zeros(target.shape, bool))
    assert masked.loss(pose) == pytest.approx(expected, rel=1e-12)
    # with the edge cue as well: both terms add
    both = Problem(None, target, camera(), GROUND_TRUTH.translation,
                   replace(params, cues=CueParams(intensity_weight=WEIGHT, edge_weight=0.5)),
                   prepared=problem.pmap, image=intensity_image)
    both.render(pose)
    assert both.last_render() is not None
    edge = both.level(-1).loss.edge.term(both.last_render()[1])
    assert both.loss(pose) == pytest.approx(expected + 0.5 * edge, rel=1e-12)


def test_off_costs_nothing_and_a_map_without_intensity_says_so(world, bright_world, target,
                                                               intensity_image):
    off = Problem(bright_world, target, camera(), GROUND_TRUTH.translation,
                  image=intensity_image)
    assert off.grey is None and off.pmap.intensity is not None
    assert all(type(off.level(s).loss) is LabelLoss for s in range(len(off.stages)))
    params = replace(CalibrationParams(), cues=CueParams(intensity_weight=WEIGHT))
    with pytest.raises(ValueError, match="needs the camera image"):
        Problem(bright_world, target, camera(), GROUND_TRUTH.translation, params)
    with pytest.raises(ValueError) as info:
        Problem(world, target, camera(), GROUND_TRUTH.translation, params, image=intensity_image)
    assert "no 'intensity' property" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ValueError, match="below half of loss.degenerate_loss"):
        Problem(bright_world, target, camera(), GROUND_TRUTH.translation,
                replace(params, cues=CueParams(intensity_weight=5.0)), image=intensity_image)
    with pytest.raises(ValueError, match="cues.intensity_weight"):
        CueParams(intensity_weight=-1.0)
    with pytest.raises(ValueError, match="cues.intensity_bins"):
        CueParams(intensity_bins=1)
    assert CueParams(intensity_weight=0.1).active and not CueParams().active


def test_map_ply_carries_intensity_and_files_without_it_load(tmp_path):
    rng = np.random.default_rng(3)
    xyz = rng.random((300, 3)) * 10
    label = rng.choice([40, 50, 70], 300).astype(np.uint16)
    intensity = rng.random(300).astype(np.float32)
    write_ply(tmp_path / "with.ply", LabelledCloud(xyz, label, {"intensity": intensity}))
    write_ply(tmp_path / "without.ply", LabelledCloud(xyz, label))
    names = PlyData.read(str(tmp_path / "with.ply"))["vertex"].data.dtype.names
    assert names == ("x", "y", "z", "intensity", "label")  # the scans' layout (CONTRACTS.md)
    assert PlyData.read(str(tmp_path / "without.ply"))["vertex"].data.dtype.names == \
        ("x", "y", "z", "label")
    back = read_ply(tmp_path / "with.ply")
    np.testing.assert_array_equal(back.intensity, intensity)
    np.testing.assert_array_equal(back.label, label)
    old = read_ply(tmp_path / "without.ply")
    assert old.intensity is None and prepare_map(old).intensity is None
    assert prepare_map(back).intensity is not None


def test_map_writers_keep_the_mean_intensity_per_voxel():
    # two points of one class in one voxel, one of another class in it: the majority's mean
    xyz = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.03, 0.01, 0.01],
                    [1.01, 0.01, 0.01]])
    cloud = LabelledCloud(xyz, np.array([40, 40, 70, 40], np.uint16),
                          {"intensity": np.array([0.2, 0.4, 0.9, 0.5], np.float32)})
    down = voxel_downsample(cloud, 0.5)
    order = np.argsort(down.xyz[:, 0])
    np.testing.assert_allclose(down.intensity[order], [0.3, 0.5], atol=1e-6)
    # the map builder (semcal build-map, semcal real-scene) carries it from scan to map
    rng = np.random.default_rng(4)
    scan = LabelledCloud(rng.random((2000, 3)) * 8 + [2, 0, 0],
                         np.full(2000, 40, np.uint16),
                         {"intensity": rng.random(2000).astype(np.float32)})
    result = build_map([ScanInput(scan, np.eye(4), 0.0, "0")],
                       MapBuildParams(voxel=0.5, icp=False, remove_dynamic=False))
    assert result.map.intensity is not None and len(result.map.intensity) == len(result.map)
    assert 0.3 < float(np.mean(result.map.intensity)) < 0.7
    bare = build_map([ScanInput(LabelledCloud(scan.xyz, scan.label), np.eye(4), 0.0, "0")],
                     MapBuildParams(voxel=0.5, icp=False, remove_dynamic=False))
    assert bare.map.intensity is None
