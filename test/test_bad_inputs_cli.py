"""Bad inputs to ``semcal calibrate``: one line naming the problem, exit code 1, before the work.

Each case changes one input of a working call; the last test runs the working call itself, so
the table cannot pass because everything fails. Cases run in-process (``semcal_ros.cli.main``)
and are refused before any optimisation, so the table costs seconds. The action refuses the same
things (test_bad_inputs_ros.py): both doors share :mod:`semcal_ros.engine.validation`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from semcal_ros.cli import main
from semcal_ros.io import files, ply
from semcal_ros.engine.pose import Pose, translation_error
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world, target_image

NEAR = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [0.4, -0.3, 0.2],
                              GROUND_TRUTH.body_rpy_deg() + [0.0, -1.0, 1.0])
CHEAP = {"schedule": {"max_evaluations": [60, 30, 30], "restarts": [0, 0, 0]},
         "verification": {"starts": 0}}


def params_file(path: Path, **groups: dict) -> Path:
    merged = {k: dict(v) for k, v in CHEAP.items()}
    for group, values in groups.items():
        merged.setdefault(group, {}).update(values)
    path.write_text(yaml.safe_dump({"calibrator": {"ros__parameters": {"engine": merged}}}))
    return path


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("bad_cli")
    world = street_world(step=0.12)
    ply.write_ply(d / "map.ply", world)
    files.write_label_image(d / "labels.png", target_image(camera(), world=world))
    files.write_camera_info(d / "camera_info.yaml", camera())
    files.write_pose(d / "initial.yaml", NEAR)
    params_file(d / "cheap.yaml")
    (d / "a_file").write_text("not a folder")
    return d


def argv(d: Path, **over: object) -> list[str]:
    base = {"--map": d / "map.ply", "--labels": d / "labels.png",
            "--camera-info": d / "camera_info.yaml", "--initial": d / "initial.yaml",
            "--output": d / "out" / "result.yaml", "--config": d / "cheap.yaml"}
    base.update(over)
    out = ["calibrate"]
    for k, v in base.items():
        out += [k, str(v)]
    return out + ["--quiet"]


def camera_file(d: Path, name: str, fx: float) -> Path:
    data = camera().to_camera_info_dict()
    data["camera_matrix"]["data"][0] = fx
    path = d / name
    path.write_text(yaml.safe_dump(data))
    return path


def pose_file(d: Path, name: str, text: str) -> Path:
    (d / name).write_text(text)
    return d / name


def far_pose(d: Path) -> Path:
    far = Pose(NEAR.translation + [100_000.0, 0.0, 0.0], NEAR.quaternion)
    files.write_pose(d / "far.yaml", far)
    return d / "far.yaml"


def odom_pose(d: Path) -> Path:
    data = files.pose_to_dict(NEAR, frame_id="odom")
    return pose_file(d, "odom.yaml", yaml.safe_dump(data))


#: (id, how to change the working call, text the one-line message must contain)
CASES = [
    ("negative-max-evaluations",
     lambda d: {"--config": params_file(d / "c1.yaml", schedule={"max_evaluations": [-5, 30, 30]})},
     "schedule.max_evaluations must be >= 1, got [-5, 30, 30]"),
    ("nan-near-plane",
     lambda d: {"--config": params_file(d / "c2.yaml", render={"near": float("nan")})},
     "render.near must be a finite number, got nan"),
    ("far-before-near",
     lambda d: {"--config": params_file(d / "c3.yaml", render={"near": 5.0, "far": 2.0})},
     "render.near must be in (0, far = 2.0), got 5.0"),
    ("negative-verification-noise",
     lambda d: {"--config": params_file(d / "c4.yaml", verification={"noise": -0.5})},
     "verification.noise must be >= 0, got -0.5"),
    ("translation-bound-beyond-limit",
     lambda d: {"--config": params_file(d / "c5.yaml", search={"bound_xyz": [1e9, 2.5, 2.5]})},
     "search.bound_xyz 1e+09 m is beyond what the method can search (at most 50 m)"),
    ("yaw-bound-beyond-limit",
     lambda d: {"--config": params_file(d / "c6.yaml", search={"bound_yaw_deg": 1e9})},
     "search angle bound 1e+09 deg is beyond 180 deg"),
    ("unknown-loss-kind",
     lambda d: {"--config": params_file(d / "c7.yaml", loss={"kind": "l1"})},
     "loss.kind must be one of l2, huber, mi, likelihood, balanced, not 'l1'"),
    ("last-stage-not-full-resolution",
     lambda d: {"--config": params_file(d / "c8.yaml", schedule={"scales": [4, 2, 2]})},
     "the last stage must be at full resolution (scale 1)"),
    ("unknown-parameter",
     lambda d: {"--config": params_file(d / "c9.yaml", loss={"kindd": "l2"})},
     "unknown parameter(s): loss.kindd"),
    ("parameter-of-wrong-type",
     lambda d: {"--config": params_file(d / "c10.yaml", schedule={"xatol": "small"})},
     "parameter 'schedule.xatol': cannot use 'small'"),
    ("missing-config", lambda d: {"--config": d / "nope.yaml"}, "parameter file not found"),
    ("initial-pose-in-odom", lambda d: {"--initial": odom_pose(d)},
     "is in frame 'odom' but the map is in 'map' (give the pose in the map frame)"),
    ("initial-pose-100-km-away", lambda d: {"--initial": far_pose(d)},
     "km from the map (map spans x "),
    ("initial-pose-nan", lambda d: {"--initial": pose_file(
        d, "nan.yaml", "translation: [.nan, 0, 6]\nrpy_deg: [0, 0, 0]\n")},
     "pose contains NaN or infinite values"),
    ("initial-pose-non-unit", lambda d: {"--initial": pose_file(
        d, "q.yaml", "translation: [0, 0, 6]\nrotation: [0.1, 0.2, 0.3, 0.4]\n")},
     "not a unit quaternion"),
    ("initial-pose-not-yaml", lambda d: {"--initial": pose_file(d, "bad.yaml", "a: [1,\n")},
     "invalid YAML"),
    ("output-under-a-file", lambda d: {"--output": d / "a_file" / "result.yaml"},
     "a_file is not a folder"),
    ("output-is-a-folder", lambda d: {"--output": d}, "is a folder, not a file"),
    ("overlay-under-a-file", lambda d: {"--output": d / "r.yaml", "--overlay":
                                        d / "a_file" / "o.png"}, "--overlay"),
    ("camera-nan-focal-length", lambda d: {"--camera-info": camera_file(d, "nan_k.yaml",
                                                                         float("nan"))},
     "K contains NaN or infinite values"),
    ("camera-negative-focal-length", lambda d: {"--camera-info": camera_file(d, "neg_k.yaml",
                                                                              -480.0)},
     "focal length"),
    ("camera-info-missing-field", lambda d: {"--camera-info": pose_file(
        d, "ci.yaml", "image_width: 960\n")}, "camera_info is missing field"),
    ("labels-wrong-size", lambda d: {"--labels": _small_labels(d)},
     "label image is 480x300 but camera_info says 960x600"),
    ("map-missing", lambda d: {"--map": d / "nope.ply"}, "map file not found"),
    ("map-not-a-ply", lambda d: {"--map": pose_file(d, "bad.ply", "hello")},
     "not a readable PLY file"),
    ("map-with-nan-points", lambda d: {"--map": _nan_map(d)}, "NaN or infinite points"),
    ("negative-seed", lambda d: {"--seed": -3}, "--seed must be >= 0, got -3"),
]


def _small_labels(d: Path) -> Path:
    files.write_label_image(d / "small.png", np.zeros((300, 480), np.uint8))
    return d / "small.png"


def _nan_map(d: Path) -> Path:
    cloud = ply.read_ply(d / "map.ply")
    cloud.xyz[:3] = np.nan
    ply.write_ply(d / "nan.ply", cloud)
    return d / "nan.ply"


@pytest.mark.parametrize("change,expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_cli_refuses_before_the_work(case, capsys, monkeypatch, change, expected):
    import semcal_ros.engine.search

    started: list[bool] = []
    real_calibrate = semcal_ros.engine.search.calibrate

    def watched(*args, **kwargs):
        started.append(True)
        return real_calibrate(*args, **kwargs)

    monkeypatch.setattr(semcal_ros.engine.search, "calibrate", watched)
    code = main(argv(case, **change(case)))
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert err.count("\n") == 0, err  # one line, no traceback
    assert err.startswith("semcal calibrate: error: ") and expected in err, err
    assert not started, "refused only after the calibration had started"
    assert not (case / "out" / "result.yaml").exists()


def test_cli_degenerate_result_is_an_error_not_a_result(case, capsys):
    """Every view degenerate (coverage threshold above any view's): the yaw search skips the
    initial-view check, so the engine returns its best, loss = the degenerate value."""
    config = params_file(case / "degenerate.yaml", loss={"min_coverage": 1.0},
                         search={"yaw_search": True, "yaw_search_keep": 1})
    out = case / "degenerate" / "result.yaml"
    code = main(argv(case, **{"--config": config, "--output": out}))
    err = capsys.readouterr().err.strip()
    assert code == 1 and err.count("\n") == 0, err
    assert "calibration failed: " in err and "loss 10" in err, err
    assert not out.exists()


def test_cli_good_call_after_the_table(case, capsys):
    out = case / "out" / "result.yaml"
    assert main(argv(case)) == 0, capsys.readouterr().err
    assert translation_error(files.read_pose(out), GROUND_TRUTH) < 0.3


# --- the shared checks themselves (both doors call these) ---------------------------------------
def test_validation_checks(tmp_path):
    from semcal_ros.engine import validation as v
    from semcal_ros.engine.params import CalibrationParams

    assert v.output_problems(tmp_path / "new" / "deeper" / "r.yaml", "--output") == []
    (tmp_path / "f").write_text("x")
    assert v.output_problems(tmp_path / "f" / "r.yaml", "--output") == [
        f"--output {tmp_path / 'f' / 'r.yaml'}: {tmp_path / 'f'} is not a folder"]
    assert "is a folder" in v.output_problems(tmp_path, "--output")[0]

    box = (np.array([0.0, 0.0, 0.0]), np.array([10.0, 10.0, 5.0]))
    params = CalibrationParams()
    assert v.reach_problems([5, 5, 2], box, params) == []
    assert v.reach_problems([130, 5, 2], box, params) == []  # 120 m off: still within reach
    assert "200 m from the map" in v.reach_problems([210, 5, 2], box, params)[0]
    assert v.reach_problems([0, 0, 0], None, params) == ["the map has no point"]

    assert v.result_problems(0.01, params) == []
    for loss in (10.0, 12.0, float("nan")):
        assert "degenerate" in v.result_problems(loss, params)[0]

    k = np.array([[480.0, 0, 479.5], [0, 480.0, 299.5], [0, 0, 1]])
    assert v.camera_problems(960, 600, k, np.zeros(5)) == []
    nan_k = k.copy()
    nan_k[0, 0] = np.nan
    assert v.camera_problems(960, 600, nan_k, np.zeros(5)) == ["K contains NaN or infinite values"]
    assert v.camera_problems(960, 600, np.zeros((3, 3)), np.zeros(5)) == [
        "K is all zeros (camera not calibrated)"]
    assert v.camera_problems(0, 600, k, [np.inf, 0, 0, 0, 0]) == [
        "image size 0x600 is empty", "distortion coefficients contain NaN or infinite values"]

    assert v.bound_problems([0, 0, 0], [0, 0, 0]) == []  # 0 = the node default
    assert v.bound_problems([50, 1, 1], [180, 1, 1]) == []  # the limits themselves are allowed
    assert v.bound_problems([1e9, 0, 0], [0, 0, 181]) == [
        "bound_translation_m.x 1e+09 m is beyond what the search can cover (at most 50 m)",
        "bound_rpy_deg.z 181 deg is beyond what the search can cover (at most 180 deg)"]
    assert v.bound_problems([-1, np.nan, 0], [0, 0, 0]) == [
        "bound_translation_m.x must be >= 0 (0 = node default), got -1.0",
        "bound_translation_m.y must be >= 0 (0 = node default), got nan"]
    assert v.pose_problems([0, 0, np.inf], [0, 0, 0, 1]) == [
        "initial_pose contains NaN or infinite values"]
    assert v.frame_problems("odom", "map") and v.frame_problems("", "map") == []
    with pytest.raises(ValueError, match="^x: a; b$"):
        v.check(["a", "b"], "x: ")
