"""Lens models (docs/lenses.md): plumb_bob, rational_polynomial and equidistant project as OpenCV
does over the whole image, a fisheye draws what lies behind its image plane, unprojection is the
inverse of projection, CameraInfo carries the model, and a fisheye scene calibrates."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import yaml

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.pose import rotation_error_deg, translation_error

K = np.array([[420.0, 0.0, 481.3], [0.0, 415.0, 297.8], [0.0, 0.0, 1.0]])

#: each model with coefficients of the size a real calibration gives (tangential terms included)
CAMERAS = {
    "plumb_bob": CameraModel(960, 600, K, np.array([-0.12, 0.03, 0.0012, -0.0008, -0.002])),
    "rational_polynomial": CameraModel(960, 600, K, np.array(
        [0.25, 0.02, 0.0009, -0.0006, 0.001, 0.62, 0.07, 0.002]), model="rational_polynomial"),
    "equidistant": CameraModel(960, 600, np.array([[300.0, 0, 479.5], [0, 301.0, 299.5],
                                                   [0, 0, 1]]),
                               np.array([0.021, -0.006, 0.0011, -0.0001]), model="equidistant"),
    "fisheye_185": CameraModel.fisheye_fov(960, 600, 185.0),
    "wide_120": CameraModel.rational_fov(960, 600, 120.0),
}


def _whole_image(cam: CameraModel, step: float = 6.0) -> np.ndarray:
    """A pixel grid over the whole image, borders included."""
    u = np.append(np.arange(-0.49, cam.width - 0.5, step), cam.width - 0.51)
    v = np.append(np.arange(-0.49, cam.height - 0.5, step), cam.height - 0.51)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], 1)


def _opencv(cam: CameraModel, pts: np.ndarray) -> np.ndarray:
    if cam.fisheye:
        out, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                           cam.k, cam.d)
    else:
        out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.k, cam.d)
    return out.reshape(-1, 2)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_projection_matches_opencv_over_the_whole_image(name):
    """Points whose rays pass through every part of the image, at ranges 0.5-80 m, project to
    the pixel OpenCV gives (0.01 px); OpenCV's fisheye formula holds only in front of the image
    plane (it takes theta = atan(r / z)), so there the comparison is restricted to z > 0."""
    cam = CAMERAS[name]
    uv = _whole_image(cam)
    rays, ok = cam.unproject(uv)
    assert ok.all(), f"{(~ok).sum()} pixels not reached"
    ranges = np.random.default_rng(1).uniform(0.5, 80.0, len(rays))
    pts = rays * ranges[:, None]
    ours, seen = cam.project(pts)
    assert seen.all()
    front = pts[:, 2] > 1e-3
    err = np.abs(ours[front] - _opencv(cam, pts[front])).max()
    assert err < 0.01, f"{name}: {err:.4f} px from OpenCV"
    # the grid came back where it started: the inverse holds everywhere, beyond 90 deg included
    np.testing.assert_allclose(ours, uv, atol=0.01)
    if name == "fisheye_185":
        assert (~front).sum() > 1000  # the fisheye's image really reaches behind its image plane


@pytest.mark.parametrize("name", ["plumb_bob", "rational_polynomial", "equidistant"])
def test_random_points_match_opencv_where_they_land(name):
    """Independent of unproject: random points in front of the camera, those landing in the
    image agree with OpenCV to 0.01 px, and the in-image mask agrees with OpenCV's pixels."""
    cam = CAMERAS[name]
    pts = np.random.default_rng(2).uniform([-30, -20, 0.2], [30, 20, 40], (20000, 3))
    ours, seen = cam.project(pts)
    ref = _opencv(cam, pts)
    assert seen.sum() > 2000
    assert np.abs(ours[seen] - ref[seen]).max() < 0.01
    inside = (ref[:, 0] > -0.5) & (ref[:, 0] < 959.5) & (ref[:, 1] > -0.5) & (ref[:, 1] < 599.5)
    # a pinhole model refuses points beyond its fold (OpenCV folds them back into the picture)
    assert (seen & ~inside).sum() == 0


def test_fisheye_draws_behind_the_image_plane_pinholes_refuse():
    fish, wide, pin = CAMERAS["fisheye_185"], CAMERAS["wide_120"], CAMERAS["plumb_bob"]
    # 92 deg off the axis to the right, level: behind the image plane (z < 0)
    a = np.radians(92.0)
    p = np.array([[np.sin(a) * 10.0, 0.0, np.cos(a) * 10.0]])
    uv, seen = fish.project(p)
    assert seen[0] and p[0, 2] < 0
    # equidistant: the image radius is f * theta_d(theta), on the row of the principal point
    t = a
    k1, k2, k3, k4 = fish.d
    theta_d = t * (1 + k1 * t**2 + k2 * t**4 + k3 * t**6 + k4 * t**8)
    np.testing.assert_allclose(uv[0], [fish.cx + fish.fx * theta_d, fish.cy], atol=1e-9)
    assert uv[0, 0] > fish.width - 30  # near the right edge of a 185 deg image
    for cam in (wide, pin):
        assert not cam.project(p)[1][0]
    # a point straight behind the camera is beyond the fisheye's limit (the corner angle)
    assert fish.render_limit() < np.radians(115.0)
    assert not fish.project(np.array([[0.0, 0.0, -5.0]]))[1][0]
    assert fish.half_fov_deg() == pytest.approx(92.5, abs=1e-6)
    assert wide.half_fov_deg() == pytest.approx(60.0, abs=1e-6)


def test_camera_info_yaml_round_trip_and_unknown_model_refused(tmp_path):
    from semcal_ros.io.files import read_camera_info, write_camera_info

    for name in ("equidistant", "wide_120", "plumb_bob"):
        cam = CAMERAS[name]
        write_camera_info(tmp_path / "ci.yaml", cam)
        data = yaml.safe_load((tmp_path / "ci.yaml").read_text())
        assert data["distortion_model"] == cam.model
        assert len(data["distortion_coefficients"]["data"]) == {"plumb_bob": 5,
                                                                "rational_polynomial": 8,
                                                                "equidistant": 4}[cam.model]
        back = read_camera_info(tmp_path / "ci.yaml")
        assert back.model == cam.model
        np.testing.assert_array_equal(back.d, cam.d)
    data["distortion_model"] = "fov"
    with pytest.raises(ValueError, match="unsupported distortion model 'fov'"):
        CameraModel.from_camera_info_dict(data)
    with pytest.raises(ValueError, match="rational_polynomial"):
        CameraModel(960, 600, K, np.arange(8) * 0.01)  # 8 coefficients under plumb_bob


def test_calibrate_cli_refuses_an_unknown_model_in_one_line(tmp_path, capsys):
    from semcal_ros.cli import main

    data = CAMERAS["equidistant"].to_camera_info_dict()
    data["distortion_model"] = "kannala_brandt"
    (tmp_path / "ci.yaml").write_text(yaml.safe_dump(data))
    code = main(["calibrate", "--map", str(tmp_path / "map.ply"), "--labels",
                 str(tmp_path / "l.png"), "--camera-info", str(tmp_path / "ci.yaml"),
                 "--initial", str(tmp_path / "i.yaml"), "--output", str(tmp_path / "r.yaml"),
                 "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and err.count("\n") == 0, err
    assert "unsupported distortion model 'kannala_brandt'" in err, err


def test_ros_camera_info_accepts_equidistant_and_refuses_unknown_in_one_line():
    pytest.importorskip("rclpy")
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CameraInfo

    from semcal_ros.ros import conversions as conv

    for name in ("equidistant", "wide_120"):
        cam = replace(CAMERAS[name], frame_id="north_optical")
        msg = deserialize_message(serialize_message(conv.model_to_camera_info(cam)), CameraInfo)
        assert msg.distortion_model == cam.model and len(msg.d) == cam.d.size
        back = conv.camera_info_to_model(msg)
        assert back.model == cam.model and back.frame_id == "north_optical"
        pts = np.random.default_rng(4).uniform([-20, -10, -3], [20, 10, 30], (500, 3))
        np.testing.assert_array_equal(back.project(pts)[0], cam.project(pts)[0])
    msg.distortion_model = "fov"
    with pytest.raises(ValueError) as info:
        conv.camera_info_to_model(msg)
    assert "unsupported distortion model 'fov'" in str(info.value)
    assert "\n" not in str(info.value)
    msg.distortion_model = "equidistant"
    msg.d = [0.01, 0.0, 0.0, 0.0, 0.3]  # a fifth coefficient the model does not have
    with pytest.raises(ValueError, match="equidistant takes 4 distortion coefficients"):
        conv.camera_info_to_model(msg)


@pytest.mark.slow
def test_fisheye_scene_calibrates_from_a_near_start(scene_factory):
    """A small fisheye junction (185 deg): its camera_info is equidistant, its label image the
    lens' ray cast, and a start 0.4 m / 0.8 deg off comes back within 8 cm / 0.25 deg."""
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply
    from semcal_ros.engine.search import calibrate
    from semcal_ros.engine.params import CalibrationParams, ScheduleParams, VerificationParams
    from semcal_ros.engine.pose import Pose

    scene = scene_factory("junction", 0, "ideal", lens="fisheye", write_bag=False,
                          write_scans=False)
    camera = read_camera_info(scene / "camera_info.yaml")
    assert camera.model == "equidistant" and camera.half_fov_deg() == pytest.approx(92.5)
    assert yaml.safe_load((scene / "scene.yaml").read_text())["options"]["lens"] == "fisheye"
    truth = read_pose(scene / "ground_truth.yaml")
    start = Pose.from_body_rpy_deg(truth.translation + [0.3, -0.2, 0.15],
                                   truth.body_rpy_deg() + [0.0, 0.6, -0.5])
    params = replace(CalibrationParams(), schedule=ScheduleParams(
        scales=(4, 1), simplex=(1.0, 0.05), fatol=(1e-4, 1e-6), max_evaluations=(120, 30),
        restarts=(0, 0)), verification=VerificationParams(starts=0))
    result = calibrate(read_ply(scene / "map.ply"), read_label_image(scene / "labels.png"),
                       camera, start, params, seed=0)
    dt, dr = translation_error(result.pose, truth), rotation_error_deg(result.pose, truth)
    assert dt < 0.08 and dr < 0.25, f"{dt * 100:.1f} cm, {dr:.3f} deg"
