"""Camera models are checked where every door builds them (issue 34): each distortion model takes
its own coefficient count (plumb_bob 5, rational_polynomial 8, equidistant 4). Fewer is refused
in one line; more is refused when a coefficient beyond the count is non-zero, and accepted with
one note when they are zeros. The doors: the camera_info YAML of `semcal calibrate`, `semcal
check` and `semcal real-scene`, and the CameraInfo messages of the nodes (the process test is in
test_safety_nodes.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import yaml

from semcal_ros.engine import camera as camera_module
from semcal_ros.engine.camera import CameraModel

K = np.array([[480.0, 0.0, 479.5], [0.0, 480.0, 299.5], [0.0, 0.0, 1.0]])

#: (model, coefficients, the refusal)
BAD = [
    ("equidistant", [0.02, -0.005],
     "equidistant takes 4 distortion coefficients (k1 k2 k3 k4), got 2"),
    ("rational_polynomial", [0.2, 0.01, 0.0],
     "rational_polynomial takes 8 distortion coefficients (k1 k2 p1 p2 k3 k4 k5 k6), got 3"),
    ("plumb_bob", [-0.1, 0.02, 0.001, 0.0],
     "plumb_bob takes 5 distortion coefficients (k1 k2 p1 p2 k3), got 4"),
    ("equidistant", [0.02, -0.005, 0.0005, 0.0, 0.3],
     "equidistant takes 4 distortion coefficients (k1 k2 k3 k4), got 5 with non-zero ones"),
]


@pytest.mark.parametrize("model,d,expected", BAD, ids=[f"{m}-{len(d)}" for m, d, _ in BAD])
def test_a_wrong_coefficient_count_is_refused(model, d, expected):
    with pytest.raises(ValueError) as info:
        CameraModel(960, 600, K, np.array(d), "cam", model)
    assert expected in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_trailing_zeros_are_accepted_and_said_once(caplog):
    camera_module._said.clear()
    with caplog.at_level(logging.WARNING, logger="semcal_ros.engine.camera"):
        for _ in range(3):  # a CameraInfo stream: the note once
            cam = CameraModel(960, 600, K, np.array([-0.1, 0.02, 0.001, -0.002, 0.01, 0.0, 0.0,
                                                     0.0]))
    assert cam.d.tolist() == [-0.1, 0.02, 0.001, -0.002, 0.01]
    notes = [r.getMessage() for r in caplog.records]
    assert notes == ["plumb_bob takes 5 distortion coefficients (k1 k2 p1 p2 k3): the 3 zeros "
                     "beyond them ignored"], notes
    # exactly the count, or none at all (no distortion), needs no note
    CameraModel(960, 600, K, np.array([0.02, -0.005, 0.0005, 0.0]), "cam", "equidistant")
    assert CameraModel(960, 600, K, np.array([]), "cam", "equidistant").d.tolist() == [0.0] * 4
    assert len(caplog.records) == 1


def _camera_info(path, model: str, d: list[float]):
    data = CameraModel(960, 600, K, np.zeros(5)).to_camera_info_dict()
    data["distortion_model"] = model
    data["distortion_coefficients"] = {"rows": 1, "cols": len(d), "data": d}
    path.write_text(yaml.safe_dump(data))
    return path


def _run(capsys, argv: list[str]) -> tuple[int, str]:
    from semcal_ros.cli import main

    code = main(argv)
    return code, capsys.readouterr().err


def test_every_cli_door_refuses_a_fisheye_with_two_coefficients(tmp_path, capsys):
    import cv2

    info = _camera_info(tmp_path / "ci.yaml", "equidistant", [0.02, -0.005])
    image = tmp_path / "image.png"
    cv2.imwrite(str(image), np.zeros((600, 960, 3), np.uint8))
    missing = str(tmp_path / "missing")
    doors = {
        "calibrate": ["calibrate", "--map", missing, "--labels", missing, "--camera-info",
                      str(info), "--initial", missing, "--output", str(tmp_path / "out.yaml")],
        "check": ["check", "--map", missing, "--labels", missing, "--camera-info", str(info),
                  "--calibration", missing],
        "real-scene": ["real-scene", "--image", str(image), "--scans", missing,
                       "--camera-info", str(info), "--initial", missing, "--cloud-labels",
                       "geometric", "--labels", missing, "--out", str(tmp_path / "scene")],
    }
    for door, argv in doors.items():
        code, err = _run(capsys, argv)
        assert code == 1, (door, err)
        assert err.count("\n") == 1 and "Traceback" not in err, (door, err)
        assert "equidistant takes 4 distortion coefficients (k1 k2 k3 k4), got 2" in err, \
            (door, err)
        assert str(info) in err, (door, err)


def test_the_camera_info_message_door_refuses_it_in_one_line():
    pytest.importorskip("rclpy")
    from semcal_ros.ros import conversions as conv

    msg = conv.model_to_camera_info(CameraModel(960, 600, K, np.zeros(5)))
    msg.distortion_model, msg.d = "rational_polynomial", [0.2, 0.01, 0.0]
    with pytest.raises(ValueError) as info:
        conv.camera_info_to_model(msg)
    assert str(info.value) == ("rational_polynomial takes 8 distortion coefficients (k1 k2 p1 p2 "
                               "k3 k4 k5 k6), got 3"), str(info.value)
    msg.distortion_model, msg.d = "plumb_bob", []  # no coefficients: no distortion
    assert conv.camera_info_to_model(msg).d.tolist() == [0.0] * 5
