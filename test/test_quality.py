"""The quality report: agreement, per-axis uncertainty and the verdict, on scenes where the right
answer is known; and the network-like label noise the report and the loss are measured with."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
from semcal_ros.io.ply import read_ply
from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, KITTI_ID
from semcal_ros.engine.search import calibrate
from semcal_ros.engine.params import CalibrationParams, ScheduleParams, VerificationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.quality import QualityParams, assess, label_agreement
from semcal_ros.engine.results import QualityReport
from semcal_tools.scenes.labelnoise import NOISE_MODELS, add_network_noise
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world, target_image

ROAD, BUILDING = CITYSCAPES_ID["road"], CITYSCAPES_ID["building"]
TINY = dict(scans=6, horizontal_step_deg=1.0, write_bag=False)
#: One coarse stage and a short full-resolution one: the verdict, not the search, is under test.
CHEAP = CalibrationParams(schedule=ScheduleParams(
    scales=(4, 1), simplex=(1.0, 0.03), fatol=(1e-4, 1e-6), max_evaluations=(120, 40),
    restarts=(0, 0)), verification=VerificationParams(starts=2))


def _scene(folder: Path) -> tuple[LabelledCloud, np.ndarray, object, Pose]:
    return (read_ply(folder / "map.ply"), read_label_image(folder / "labels.png"),
            read_camera_info(folder / "camera_info.yaml"), read_pose(folder / "ground_truth.yaml"))


def test_label_agreement_counts_pixels_both_sides_labelled():
    target = np.full((4, 5), ROAD, np.uint8)
    target[0] = BUILDING
    rendered = target.copy()
    rendered[0, :2] = ROAD  # 2 of 5 building pixels wrong
    rendered[3] = INVALID  # nothing drawn: not counted
    overall, per_class = label_agreement(rendered, target)
    assert overall == pytest.approx(13 / 15)
    assert per_class == {"building": pytest.approx(3 / 5), "road": pytest.approx(1.0)}
    assert label_agreement(np.full_like(target, INVALID), target) == (0.0, {})


def test_good_on_the_ideal_junction_with_every_axis_pinned_down(demo_scene):
    cloud, labels, cam, truth = _scene(demo_scene)
    start = Pose.from_body_rpy_deg(truth.translation + [0.6, -0.5, 0.3],
                                   truth.body_rpy_deg() + [0.0, 1.0, -1.0])
    res = calibrate(cloud, labels, cam, start, CHEAP, seed=0)
    q = res.quality
    assert q.verdict == "good", q.summary()
    assert q.agreement > 0.9 and q.coverage > 0.5
    qp = CHEAP.quality
    assert max(q.uncertainty_translation_m) <= qp.max_translation_m
    assert max(q.uncertainty_rpy_deg[1:]) <= qp.max_rotation_deg
    # the report travels with the result: the YAML group and the one-line summary
    d = res.to_dict()["quality"]
    assert d["verdict"] == "good" and len(d["uncertainty_translation_m"]) == 3
    assert "GOOD" in q.summary()


def test_inconclusive_on_a_flat_road_naming_the_axis_along_it():
    """A map of only road and lane markings (one class once aligned): moving along the road
    changes nothing the camera sees, so x (the road's direction) is named as unconstrained."""
    world = street_world(step=0.12)
    keep = np.isin(world.label, [KITTI_ID["road"], KITTI_ID["lane-marking"]])
    road = LabelledCloud(world.xyz[keep], world.label[keep])
    cam = camera()
    dense = street_world(step=0.06, seed=5)  # another sampling of the same road: no exact match
    dense = dense.select(np.isin(dense.label, [KITTI_ID["road"], KITTI_ID["lane-marking"]]))
    target = target_image(cam, world=dense)
    problem = Problem(road, target, cam, GROUND_TRUTH.translation)
    q = assess(problem, GROUND_TRUTH)
    assert q.verdict == "inconclusive", q.summary()
    assert "x" in q.unconstrained and "x" in q.reason
    assert q.uncertainty_translation_m[0] > problem.params.quality.max_translation_m


def test_failed_when_the_map_is_of_another_scene(scene_factory):
    junction = scene_factory("junction", 3, "ideal", **TINY)
    arterial = scene_factory("arterial", 1, "ideal", **TINY)
    _, labels, cam, truth = _scene(junction)
    other_map = read_ply(arterial / "map.ply")
    q = assess(Problem(other_map, labels, cam, truth.translation), truth)
    assert q.verdict == "failed", q.summary()
    assert "agree" in q.reason


def test_failed_when_the_pose_is_20_m_off(scene_factory):
    junction = scene_factory("junction", 3, "ideal", **TINY)
    cloud, labels, cam, truth = _scene(junction)
    problem = Problem(cloud, labels, cam, truth.translation)
    off = Pose.from_body_rpy_deg(truth.translation + [14.0, 14.0, 0.0], truth.body_rpy_deg())
    q = assess(problem, off)
    assert q.verdict == "failed", q.summary()
    assert assess(problem, truth).verdict != "failed"


def test_runs_that_disagree_fail_the_result():
    """A refined run in another basin with a loss as low as the result's: the data cannot decide."""
    from semcal_ros.engine.results import RunResult

    world = street_world(step=0.12)
    cam = camera()
    problem = Problem(world, target_image(cam, world=world), cam, GROUND_TRUTH.translation)
    far = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [1.0, 0, 0], GROUND_TRUTH.body_rpy_deg())
    loss, floor = problem.loss(GROUND_TRUTH), problem.floor(GROUND_TRUTH)
    runs = [RunResult(GROUND_TRUTH, GROUND_TRUTH, loss, 10, loss, True, 0),
            RunResult(far, far, loss + 0.01 * (loss - floor), 10, loss, True, 1)]
    q = assess(problem, GROUND_TRUTH, runs)
    assert q.verdict == "failed" and "runs disagree" in q.reason
    runs[1] = RunResult(far, far, loss + 0.05, 10, loss + 0.05, True, 1)  # clearly worse
    assert assess(problem, GROUND_TRUTH, runs).verdict == "good"


def test_quality_parameters_are_checked_by_name():
    with pytest.raises(ValueError, match="quality.max_translation_m"):
        QualityParams(max_translation_m=0.0)
    with pytest.raises(ValueError, match="quality.rise"):
        QualityParams(rise=float("nan"))
    assert isinstance(CalibrationParams().quality, QualityParams)
    assert QualityReport.__dataclass_fields__["verdict"]


@pytest.mark.parametrize("model", sorted(NOISE_MODELS))
def test_network_noise_is_structured_and_seeded(model):
    world = street_world(step=0.12)
    labels = target_image(camera(), world=world)
    a = add_network_noise(labels, np.random.default_rng(3), NOISE_MODELS[model])
    b = add_network_noise(labels, np.random.default_rng(3), NOISE_MODELS[model])
    np.testing.assert_array_equal(a, b)
    changed = a != labels
    assert 0.005 < changed.mean() < 0.3
    # errors sit at class boundaries and in confused regions, not spread like salt and pepper
    from scipy.ndimage import binary_opening
    assert binary_opening(changed).sum() > 0.5 * changed.sum()
    assert set(np.unique(a)) <= set(np.unique(labels)) | {CITYSCAPES_ID[n] for n in
                                                          ("terrain", "road", "building",
                                                           "vegetation")}


def test_named_noise_models_and_a_clear_error_for_unknown_ones():
    from semcal_tools.scenes.labelnoise import noisy_labels

    labels = target_image(camera(), world=street_world(step=0.12))
    assert (noisy_labels(labels, "legacy", 2) != labels).any()
    assert (noisy_labels(labels, "network", 2) != labels).any()
    with pytest.raises(ValueError, match="label noise must be legacy or one of network"):
        noisy_labels(labels, "gaussian")


@pytest.mark.slow
def test_a_start_beyond_the_measured_basin_is_named_and_never_good(demo_scene):
    """The synthetic junction, judged at its true pose: from a start inside the measured basin
    the verdict is good; from one 4 m / 31 deg away it is at most inconclusive and the reason
    names the start and the basin's bounds; with the yaw search the yaw no longer counts."""
    from dataclasses import replace

    cloud, labels, cam, truth = _scene(demo_scene)
    problem = Problem(cloud, labels, cam, truth.translation)
    near = Pose.from_body_rpy_deg(truth.translation + [1.0, -2.0, 0.5],
                                  truth.body_rpy_deg() + [0.0, 3.0, -4.0])
    far = Pose.from_body_rpy_deg(truth.translation + [4.0, 1.0, 0.0],
                                 truth.body_rpy_deg() + [0.0, 2.0, 31.0])
    q = assess(problem, truth, start=near)
    assert q.verdict == "good", q.summary()
    assert not q.start_outside_basin and q.start_offset[0] == pytest.approx(2.0, abs=1e-6)
    q = assess(problem, truth, start=far)
    assert q.verdict == "inconclusive" and q.start_outside_basin, q.summary()
    assert "the start was 4.0 m / 31 deg yaw / 2.0 deg pitch from the result" in q.reason
    assert "beyond the measured basin (2.5 m per axis, 5 deg yaw, 5 deg pitch)" in q.reason
    d = q.to_dict()
    assert d["start_outside_basin"] is True
    assert d["start_offset"]["yaw_deg"] == pytest.approx(31.0, abs=1e-3)
    # heading unknown: the yaw search covers any yaw, so a start off only in yaw is inside
    yaw_only = Pose.from_body_rpy_deg(truth.translation + [1.0, 0.0, 0.0],
                                      truth.body_rpy_deg() + [0.0, 0.0, -150.0])
    searched = replace(problem.params, search=replace(problem.params.search, yaw_search=True))
    problem.params = searched
    assert assess(problem, truth, start=yaw_only).verdict == "good"
    q = assess(problem, truth, start=far)  # still 4 m off in x
    assert q.start_outside_basin and "any yaw (yaw search)" in q.reason


def test_a_failed_verdict_stays_failed_and_also_names_the_start(scene_factory):
    junction = scene_factory("junction", 3, "ideal", **TINY)
    cloud, labels, cam, truth = _scene(junction)
    problem = Problem(cloud, labels, cam, truth.translation)
    off = Pose.from_body_rpy_deg(truth.translation + [14.0, 14.0, 0.0], truth.body_rpy_deg())
    q = assess(problem, off, start=truth)
    assert q.verdict == "failed" and q.start_outside_basin, q.summary()
    assert "check the start" in q.reason and "14.0 m" in q.reason


def test_basin_bounds_are_checked_by_name():
    with pytest.raises(ValueError, match="quality.basin_yaw_deg"):
        QualityParams(basin_yaw_deg=0.0)


def test_class_evidence_gives_each_class_its_share_coverage_and_agreement():
    """Which classes of the map to trust: per class of the labels (sky aside), its share of the
    labelled pixels, how much of it the map covers, how much of that agrees; largest first."""
    from semcal_ros.engine.quality import class_evidence
    from semcal_ros.engine.results import ClassEvidence, QualityReport

    road, building, sky = CITYSCAPES_ID["road"], CITYSCAPES_ID["building"], CITYSCAPES_ID["sky"]
    target = np.array([[road, road, road, road], [building, building, sky, INVALID]], np.uint8)
    drawn = np.array([[road, road, building, INVALID], [building, INVALID, road, road]],
                     np.uint8)
    ev = class_evidence(drawn, target)
    assert [c.name for c in ev] == ["road", "building"]
    assert ev[0] == ClassEvidence("road", 4 / 6, 3 / 4, 2 / 3)
    assert ev[1] == ClassEvidence("building", 2 / 6, 1 / 2, 1.0)
    report = QualityReport("good", "", 0.75, {}, 0.7, (0, 0, 0), (0, 0, 0),
                           classes=(ClassEvidence("road", 0.6, 0.9, 0.9),
                                    ClassEvidence("building", 0.3, 0.5, 0.2),
                                    ClassEvidence("pole", 0.005, 1.0, 0.0)))
    line = report.classes_line()
    assert line.startswith("classes, agree (covered): road 90 % (90 % covered), building 20 %")
    assert "pole" not in line and "disagree on most of their pixels here: building (" in line
    assert report.to_dict()["classes"][1] == {"class": "building", "share": 0.3,
                                              "coverage": 0.5, "agreement": 0.2}
