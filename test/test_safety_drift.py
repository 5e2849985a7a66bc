"""The drift estimate's size (issue 34): `semcal demo`'s knock (0.3 deg pan, 5 cm along the
camera's x axis) on the small junction is estimated within 30 % of its size in translation and
rotation (it came out 2.2 cm / 0.13 deg: the coarse search at 1/4 resolution, where 0.3 deg is
0.6 px, found that the camera moved but not how far; a counted drift is now sized at full
resolution, docs/drift.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from semcal_ros.engine.drift import DriftChecker, DriftParams
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import rotation_error_deg, translation_error
from semcal_ros.io import files, ply
from semcal_tools.live_demo import KNOCK_DEG, KNOCK_M, knocked
from semcal_tools.scenes import SIZES
from semcal_tools.scenes.generate import camera_view


@pytest.fixture(scope="module")
def knock(demo_scene: Path):
    truth = files.read_pose(demo_scene / "ground_truth.yaml")
    moved = knocked(truth)
    assert translation_error(moved, truth) == pytest.approx(KNOCK_M)
    assert rotation_error_deg(moved, truth) == pytest.approx(KNOCK_DEG)
    cloud = ply.read_ply(demo_scene / "map.ply")
    camera = files.read_camera_info(demo_scene / "camera_info.yaml")
    return (cloud, camera, truth, files.read_label_image(demo_scene / "labels.png"),
            camera_view("junction", 0, "ideal", SIZES["small"], moved))


def _check(knock, drift: DriftParams, engine: CalibrationParams | None = None):
    cloud, camera, truth, labels, view = knock
    checker = DriftChecker(cloud, camera, truth, engine=engine, drift=drift)
    reference = checker.check(labels)
    assert reference.level == "ok" and reference.drift_rotation_deg == 0.0, reference.summary()
    return checker.check(view, reference=reference)


def test_the_demo_knock_is_sized_within_30_percent(knock):
    report = _check(knock, DriftParams())
    assert report.level == "warn", report.summary()
    assert abs(report.drift_translation_m - KNOCK_M) <= 0.3 * KNOCK_M, report.summary()
    assert abs(report.drift_rotation_deg - KNOCK_DEG) <= 0.3 * KNOCK_DEG, report.summary()


def test_the_knock_stands_out_of_its_own_uncertainty(knock):
    """The motion from the reference image (engine/label_motion.py) carries its uncertainty from
    the two image halves; the knock is many times it, and the map's depth splits the turn from
    the shift (a turn alone would absorb the 5 cm)."""
    report = _check(knock, DriftParams())
    m = report.motion
    assert m is not None and m.samples > 1000, report.summary()
    assert m.angle_deg > 5 * m.angle_sigma_deg, report.summary()
    assert m.gain > 0.5, report.summary()  # clean labels: the motion explains the change


def test_the_unchanged_image_from_its_reference_is_exactly_ok(knock):
    cloud, camera, truth, labels, _ = knock
    checker = DriftChecker(cloud, camera, truth)
    reference = checker.check(labels)
    same = checker.check(labels, reference=reference)
    assert same.level == "ok" and same.drift_translation_m == 0.0, same.summary()
    assert same.motion is not None and same.motion.cost_before < 1e-9


def test_a_turn_beyond_the_error_threshold_is_an_error(knock):
    cloud, camera, truth, labels, _ = knock
    moved = knocked(truth, deg=0.7, metres=0.0)
    view = camera_view("junction", 0, "ideal", SIZES["small"], moved)
    report = _check((cloud, camera, truth, labels, view), DriftParams())
    assert report.level == "error", report.summary()
    assert abs(report.drift_rotation_deg - 0.7) <= 0.2, report.summary()
