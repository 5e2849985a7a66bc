"""The drift estimate's size (issue 34): `semcal demo`'s knock (0.3 deg pan, 5 cm along the
camera's x axis) on the small junction is estimated within 30 % of its size in translation and
rotation (it came out 2.2 cm / 0.13 deg: the coarse search at 1/4 resolution, where 0.3 deg is
0.6 px, found that the camera moved but not how far; a counted drift is now sized at full
resolution, docs/drift.md)."""

from __future__ import annotations

from dataclasses import replace
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


def test_without_the_full_resolution_sizing_it_was_half(knock):
    """What the issue saw with the paper's L2 (size_evaluations 0: the coarse estimate is the
    size). The default likelihood sizes it closer at 1/4 resolution already (4.6 cm / 0.28 deg)."""
    l2 = replace(CalibrationParams(), loss=replace(CalibrationParams().loss, kind="l2"))
    report = _check(knock, replace(DriftParams(), size_evaluations=0), l2)
    assert report.level == "warn", report.summary()
    assert report.drift_rotation_deg < 0.7 * KNOCK_DEG or \
        report.drift_translation_m < 0.7 * KNOCK_M, report.summary()
