"""Conventions pinned: body rpy <-> optical frame, projection of a known point to a known pixel."""

import numpy as np
import pytest

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error


def camera(d=(0, 0, 0, 0, 0)) -> CameraModel:
    k = np.array([[480.0, 0, 479.5], [0, 480.0, 299.5], [0, 0, 1]])
    return CameraModel(960, 600, k, np.array(d, float))


def test_level_camera_looking_along_x_sees_forward_point_at_centre():
    pose = Pose.from_body_rpy_deg([0, 0, 5], [0, 0, 0])
    # optical z is the body's x; optical x is the body's -y (right), optical y is -z (down)
    r = pose.rotation
    np.testing.assert_allclose(r[:, 2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(r[:, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(r[:, 1], [0, 0, -1], atol=1e-12)
    uv, ok = camera().project(pose.transform_points(np.array([[10.0, 0, 5]])))
    assert ok[0]
    np.testing.assert_allclose(uv[0], [479.5, 299.5], atol=1e-9)


def test_known_point_projects_to_known_pixel_with_pitch_and_yaw():
    # camera 6 m high, yawed 90 deg (looking along +y), pitched 20 deg down
    pose = Pose.from_body_rpy_deg([2, 3, 6], [0, 20, 90])
    # a point 1 m to the camera's left of the optical axis, on the ground 10 m ahead
    ground = np.array([2 - 1.0, 3 + 6 / np.tan(np.radians(20)), 0.0])
    pc = pose.transform_points(ground[None])[0]
    assert pc[2] > 0
    assert pc[0] < 0  # left of centre
    uv, ok = camera().project(pc[None])
    assert ok[0]
    expected_u = 479.5 + 480.0 * pc[0] / pc[2]
    assert uv[0, 0] == pytest.approx(expected_u)
    assert uv[0, 1] == pytest.approx(299.5, abs=1e-6)  # the axis hits the ground point's row
    assert uv[0, 0] < 479.5


def test_positive_pitch_looks_down():
    pose = Pose.from_body_rpy_deg([0, 0, 0], [0, 10, 0])
    assert pose.rotation[2, 2] < 0  # optical z has a downward component


def test_rpy_roundtrip_and_errors():
    rpy = np.array([1.5, -7.0, 123.0])
    pose = Pose.from_body_rpy_deg([1, 2, 3], rpy)
    np.testing.assert_allclose(pose.body_rpy_deg(), rpy, atol=1e-9)
    other = Pose.from_body_rpy_deg([1, 2, 3.5], rpy + [0, 0, 0.5])
    assert translation_error(pose, other) == pytest.approx(0.5)
    assert rotation_error_deg(pose, other) == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose(Pose.from_vector(pose.vector()).quaternion, pose.quaternion)


def test_bad_quaternion_rejected():
    with pytest.raises(ValueError, match="unit quaternion"):
        Pose([0, 0, 0], [0, 0, 0, 2])
    with pytest.raises(ValueError, match="NaN"):
        Pose([np.nan, 0, 0], [0, 0, 0, 1])


def test_distortion_matches_opencv():
    import cv2
    cam = camera((-0.2, 0.05, 0.001, -0.002, 0.0))
    pts = np.array([[1.0, 0.5, 8.0], [-2.0, 1.0, 5.0], [0.1, -0.3, 3.0]])
    uv, ok = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.k, cam.d)
    assert ok.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_scaled_camera_keeps_pixel_centres():
    cam = camera()
    half = cam.scaled(2)
    assert (half.width, half.height) == (480, 300)
    p = np.array([[0.7, -0.2, 4.0]])
    full_uv, _ = cam.project(p)
    half_uv, _ = half.project(p)
    np.testing.assert_allclose((full_uv + 0.5) / 2 - 0.5, half_uv, atol=1e-9)
