"""Calibration end to end: the engine recovers a known pose; `semcal calibrate` and its errors."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import numba
import pytest
import yaml

from semcal_ros.cli import main
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import files, ply
from semcal_ros.engine.search import Cancelled, calibrate
from semcal_ros.engine.params import CalibrationParams, VerificationParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_tools.synthetic import GROUND_TRUTH, PERTURBED_START, camera

INITIAL = PERTURBED_START
NEAR = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [0.4, -0.3, 0.2],
                              GROUND_TRUTH.body_rpy_deg() + [0.0, -1.0, 1.0])


def test_recovers_known_pose(world, target):
    params = CalibrationParams(verification=VerificationParams(starts=4))
    seen = []
    res = calibrate(world, target, camera(), INITIAL, params, seed=1, progress=seen.append)
    assert translation_error(res.pose, GROUND_TRUTH) < 0.02
    assert rotation_error_deg(res.pose, GROUND_TRUTH) < 0.07  # 0.053 with the default band
    assert len(res.runs) == 5 and 1 <= res.accepted <= 5
    assert res.evaluations == len(res.history) + res.quality.evaluations > 100
    assert seen and seen[-1].evaluations <= res.evaluations
    assert res.to_dict()["verification"]["runs"] == 5


def test_cancel_stops_promptly(world, target):
    calls = []

    def should_stop():
        calls.append(1)
        return len(calls) > 20

    with pytest.raises(Cancelled):
        calibrate(world, target, camera(), INITIAL, should_stop=should_stop)
    # the check before each evaluation: the 21st says stop; a search running beside it on
    # another core (engine/workers.py) stops at its own next check, and no start begins after
    assert 21 <= len(calls) <= 20 + max(1, numba.get_num_threads())


def test_absurd_initial_guess_is_rejected(world, target):
    away = Pose.from_body_rpy_deg([0, 0, 6], [0, -80, 0])  # looking at the sky
    with pytest.raises(ValueError, match="no map point in view"):
        calibrate(world, target, camera(), away)


@pytest.fixture(scope="module")
def case(tmp_path_factory, world, target):
    d = tmp_path_factory.mktemp("case")
    ply.write_ply(d / "map.ply", world)
    files.write_label_image(d / "labels.png", target)
    files.write_camera_info(d / "camera_info.yaml", camera())
    files.write_pose(d / "initial.yaml", NEAR)  # the CLI's plumbing, not the basin, is tested here
    (d / "fast.yaml").write_text(yaml.safe_dump(
        {"calibrator": {"ros__parameters": {"engine": {"verification": {"starts": 1}}}}}))
    return d


def args(d: Path, **over) -> list[str]:
    base = {"--map": d / "map.ply", "--labels": d / "labels.png",
            "--camera-info": d / "camera_info.yaml", "--initial": d / "initial.yaml",
            "--output": d / "result.yaml", "--config": d / "fast.yaml"}
    base.update(over)
    out = ["calibrate"]
    for k, v in base.items():
        out += [k, str(v)]
    return out + ["--quiet"]


def test_cli_writes_result_overlay_and_curve(case):
    out = case / "out"
    cmd = [sys.executable, "-m", "semcal_ros.cli"] + args(
        case, **{"--output": out / "result.yaml"}) + [
        "--overlay", str(out / "overlay.png"), "--loss-curve", str(out / "curve.png")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = yaml.safe_load((out / "result.yaml").read_text())
    assert result["frame_id"] == "map" and result["child_frame_id"] == "camera_optical"
    pose = files.read_pose(out / "result.yaml")
    assert translation_error(pose, GROUND_TRUTH) < 0.05
    assert {"loss", "evaluations", "seconds", "rpy_deg", "verification"} <= set(result)
    overlay = files.read_rgb_image(out / "overlay.png")
    assert overlay.shape == (600, 960, 3)
    assert files.read_rgb_image(out / "curve.png").std() > 0


def _error_of(argv, capsys) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err  # one line
    return err


def test_cli_missing_file(case, capsys):
    assert "not found" in _error_of(args(case, **{"--map": case / "nope.ply"}), capsys)


def test_cli_map_without_label(case, capsys):
    ply.write_ply(case / "nolabel.ply", LabelledCloud(np.zeros((5, 3))))
    assert "no 'label' property" in _error_of(args(case, **{"--map": case / "nolabel.ply"}), capsys)


def test_cli_image_size_mismatch(case, capsys):
    files.write_label_image(case / "small.png", np.zeros((300, 480), np.uint8))
    msg = _error_of(args(case, **{"--labels": case / "small.png"}), capsys)
    assert "480x300" in msg and "960x600" in msg


def test_cli_nothing_in_view(case, capsys):
    files.write_pose(case / "sky.yaml", Pose.from_body_rpy_deg([0, 0, 6], [0, -80, 0]))
    assert "no map point in view" in _error_of(args(case, **{"--initial": case / "sky.yaml"}), capsys)


def test_cli_nan_points(case, world, capsys):
    bad = LabelledCloud(world.xyz.copy(), world.label)
    bad.xyz[:3] = np.nan
    ply.write_ply(case / "nan.ply", bad)
    assert "NaN" in _error_of(args(case, **{"--map": case / "nan.ply"}), capsys)


def test_cli_non_unit_quaternion(case, capsys):
    (case / "q.yaml").write_text("translation: [0, 0, 6]\nrotation: [0.1, 0.2, 0.3, 0.4]\n")
    assert "unit quaternion" in _error_of(args(case, **{"--initial": case / "q.yaml"}), capsys)


def test_cli_unknown_parameter(case, capsys):
    (case / "typo.yaml").write_text(
        "calibrator:\n  ros__parameters:\n    engine:\n      loss: {kindd: l2}\n")
    assert "kindd" in _error_of(args(case, **{"--config": case / "typo.yaml"}), capsys)


def test_cli_yaw_search_flag_reaches_the_engine(case, monkeypatch, capsys):
    """`--yaw-search` sets engine.search.yaw_search for this run (the file's setting otherwise)."""
    import semcal_ros.engine.calibration as calibration

    seen = []

    def record(*a, **kw):
        seen.append(a[4] if len(a) > 4 else kw["params"])
        raise ValueError("recorded")

    monkeypatch.setattr(calibration, "calibrate_and_draw", record)
    assert "recorded" in _error_of(args(case) + ["--yaw-search"], capsys)
    assert "recorded" in _error_of(args(case), capsys)
    assert [p.search.yaw_search for p in seen] == [True, False]
