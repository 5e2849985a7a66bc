"""Drift check (semcal_ros.engine.drift), the drift watch (semcal_ros.engine.drift_watch: the
reference and the confirmation, without ROS) and ``semcal check`` on the small junction: an
unchanged camera passes, a turned one is flagged with its drift, and what cannot be judged says
so."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from semcal_ros.engine.drift import DriftChecker, DriftParams, DriftReport
from semcal_ros.engine.drift_watch import REFERENCE_MESSAGE, DriftWatch
from semcal_ros.io import files, ply
from semcal_ros.engine.pose import Pose
from semcal_tools.scenes import SIZES
from semcal_tools.scenes.generate import camera_view


@pytest.fixture(scope="module")
def junction(demo_scene: Path):
    cloud = ply.read_ply(demo_scene / "map.ply")
    camera = files.read_camera_info(demo_scene / "camera_info.yaml")
    truth = files.read_pose(demo_scene / "ground_truth.yaml")
    return demo_scene, cloud, camera, truth, DriftChecker(cloud, camera, truth)


def turned(pose: Pose, yaw_deg: float, metres: float = 0.0) -> Pose:
    rpy = pose.body_rpy_deg() + [0.0, 0.0, yaw_deg]
    return Pose.from_body_rpy_deg(pose.translation + [metres, 0.0, 0.0], rpy)


def test_unchanged_camera_is_ok_and_a_turned_one_is_flagged_with_its_drift(junction):
    scene, _, _, truth, checker = junction
    labels = files.read_label_image(scene / "labels.png")
    reference = checker.check(labels)
    assert reference.judged and reference.evaluations > 10
    same = checker.check(labels, reference=reference)
    assert same.level == "ok" and same.drift_rotation_deg == 0.0
    moved = turned(truth, 0.4, 0.05)
    view = camera_view("junction", 0, "ideal", SIZES["small"], moved)
    report = checker.check(view, reference=reference)
    assert report.level in ("warn", "error"), report.summary()
    assert 0.2 <= report.drift_rotation_deg <= 0.6
    assert report.loss_best < report.loss_calibrated
    # the estimate moved towards the camera's new pose, not away from it
    assert abs(report.estimated.body_rpy_deg()[2] - moved.body_rpy_deg()[2]) < 0.25


def test_cannot_judge_without_an_image_or_with_a_map_out_of_view(junction):
    _, cloud, camera, truth, checker = junction
    assert checker.check(None).level == "unknown"
    away = Pose(truth.translation + [500.0, 500.0, 0.0], truth.quaternion)  # nothing in view
    blind = DriftChecker(cloud, camera, away, prepared=checker.pmap)
    report = blind.check(np.full((camera.height, camera.width), 0, np.uint8))
    assert report.level == "unknown" and "covers" in report.message
    wrong = blind.check(np.zeros((10, 10), np.uint8))
    assert wrong.level == "unknown" and "camera_info" in wrong.message


def test_drift_parameters_are_checked():
    with pytest.raises(ValueError, match="drift.bound_m"):
        DriftParams(bound_m=0)
    with pytest.raises(ValueError, match="inside the search bounds"):
        DriftParams(error_rotation_deg=2.0)


def test_semcal_check_exit_codes(demo_scene: Path, tmp_path: Path):
    """0 when the calibration holds, 3 for drift (a calibration 0.5 deg off), 1 when it cannot
    judge (calibration pointing where the map is not) - each with its verdict printed."""
    truth = files.read_pose(demo_scene / "ground_truth.yaml")
    off = tmp_path / "off.yaml"
    files.write_pose(off, turned(truth, 0.5, 0.05))
    away = tmp_path / "away.yaml"
    files.write_pose(away, Pose(truth.translation + [500.0, 0.0, 0.0], truth.quaternion))
    base = [sys.executable, "-m", "semcal_ros.cli", "check", "--map", str(demo_scene / "map.ply"),
            "--labels", str(demo_scene / "labels.png"),
            "--camera-info", str(demo_scene / "camera_info.yaml")]
    runs = {name: subprocess.run(base + ["--calibration", str(path),
                                         "--reference", str(demo_scene / "labels.png")]
                                 if name == "ok" else base + ["--calibration", str(path)],
                                 capture_output=True, text=True, timeout=120)
            for name, path in (("ok", demo_scene / "ground_truth.yaml"), ("drift", off),
                               ("away", away))}
    assert runs["ok"].returncode == 0 and runs["ok"].stdout.startswith("OK"), runs["ok"]
    assert runs["drift"].returncode == 3 and "drift:" in runs["drift"].stdout, runs["drift"]
    assert runs["away"].returncode == 1 and "CANNOT JUDGE" in runs["away"].stdout, runs["away"]
    bad = subprocess.run(base + ["--calibration", str(tmp_path / "missing.yaml")],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "Traceback" not in bad.stderr and \
        len(bad.stderr.strip().splitlines()) == 1


def _report(level: str, pose: Pose, drift_deg: float = 0.0) -> DriftReport:
    """A check's report as check_drift makes it (what the watch reads of it)."""
    return DriftReport(level, f"{level} check", pose, pose if level != "unknown" else None,
                       drift_rotation_deg=drift_deg, loss_calibrated=0.2, loss_best=0.18,
                       raw_vector=pose.vector() + 1e-3, raw_gain=0.08)


def test_drift_watch_takes_the_first_clean_check_as_reference_and_confirms_levels():
    pose = Pose.from_body_rpy_deg(np.zeros(3), [0.0, 5.0, 30.0])
    watch = DriftWatch(confirm=2)
    assert watch.observe(_report("unknown", pose)).message == "cannot judge: unknown check"
    assert watch.reference is None and not watch.referenced  # cannot judge: no reference
    first = watch.observe(_report("ok", pose, 0.05))
    assert watch.reference is not None and watch.reference.raw_gain == 0.08  # kept as checked
    assert first.report.message == REFERENCE_MESSAGE and first.report.drift_rotation_deg == 0.0
    assert first.shown == "ok" and not first.pending
    warned = watch.observe(_report("warn", pose, 0.3))  # a new level waits for confirmation
    assert warned.shown == "ok" and warned.pending and not warned.raised
    assert warned.message == "warn check (confirming 1/2)"
    confirmed = watch.observe(_report("warn", pose, 0.3))
    assert confirmed.shown == "warn" and confirmed.raised and confirmed.message == "warn check"
    error = watch.observe(_report("error", pose, 0.6))  # error after warn: confirmed anew
    assert error.shown == "warn" and error.pending
    back = watch.observe(_report("ok", pose))  # ok and unknown are shown at once
    assert back.shown == "ok" and back.report.message == "ok check"  # not a second reference
    assert watch.observe(_report("unknown", pose)).shown == "unknown"
    assert watch.checks == 7


def test_drift_watch_refuses_a_drifting_reference_and_starts_again_on_a_new_calibration():
    pose = Pose.from_body_rpy_deg(np.zeros(3), [0.0, 5.0, 30.0])
    watch = DriftWatch(confirm=2)
    watch.observe(_report("warn", pose, 0.3))  # the first judged check found drift
    assert watch.referenced and watch.reference is None  # later checks stay absolute
    assert watch.observe(_report("ok", pose)).report.message == "ok check"
    watch.observe(_report("warn", pose))
    watch.new_map()  # new map: a new reference, the streak goes on
    assert not watch.referenced and watch.streak == ["ok", "warn"]
    epoch = watch.epoch
    watch.new_calibration()  # a check that started before this is of the old calibration
    assert watch.streak == []
    stale = watch.observe(_report("ok", pose), epoch)
    assert watch.reference is None and stale.report.message == "ok check"
    assert watch.observe(_report("ok", pose), watch.epoch).report.message == REFERENCE_MESSAGE
    absolute = DriftWatch(confirm=1, take_reference=False)
    assert absolute.observe(_report("ok", pose)).report.message == "ok check"
    assert absolute.observe(_report("warn", pose)).raised  # confirm 1: raised at once
    with pytest.raises(ValueError, match="confirm"):
        DriftWatch(confirm=0)


def test_drift_watch_on_the_junction_counts_from_its_reference(junction):
    """With the real check: the first check of the unchanged image is the reference, the next
    check of the same image reports exactly no drift (docs/drift.md)."""
    scene, _, _, _, checker = junction
    labels = files.read_label_image(scene / "labels.png")
    watch = DriftWatch()
    first = watch.check(checker, labels)
    assert first.report.message == REFERENCE_MESSAGE and watch.reference is not None
    assert watch.reference.raw_vector is not None and watch.reference.evaluations > 10
    again = watch.check(checker, labels)
    assert again.shown == "ok" and again.report.drift_translation_m == 0.0
    assert again.report.loss_best <= again.report.loss_calibrated
