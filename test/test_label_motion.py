"""The camera's motion between two label images with known depth (engine/label_motion.py), on an
analytic scene: a camera 6 m above a striped ground, a wall of blocks 30 m ahead. Both label
images are ray cast exactly, so the estimate's errors are the method's own."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.label_motion import ReferenceView, estimate_motion

HEIGHT, WALL = 6.0, 30.0
ROAD, SIDEWALK, BUILDING, VEGETATION, SKY = 0, 1, 2, 8, 10


def cast(camera: CameraModel, rotation: np.ndarray, translation: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """(labels, range) seen by the camera at (rotation, translation) from the reference frame
    (x right, y down, z forward; the ground is y = HEIGHT, the wall z = WALL)."""
    vv, uu = np.mgrid[0:camera.height, 0:camera.width]
    rays, ok = camera.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float))
    d = rays @ rotation.T  # ray directions in the reference frame
    o = np.asarray(translation, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 1] > 1e-9, (HEIGHT - o[1]) / d[:, 1], np.inf)
        t_wall = np.where(d[:, 2] > 1e-9, (WALL - o[2]) / d[:, 2], np.inf)
    t = np.minimum(t_ground, t_wall)
    p = o + d * t[:, None]
    labels = np.full(len(d), SKY, np.uint8)
    ground = (t_ground <= t_wall) & np.isfinite(t_ground)
    wall = (t_wall < t_ground) & np.isfinite(t_wall) & (p[:, 1] > -4.0)
    labels[ground] = np.where(np.floor(p[ground, 0] / 3.0) % 2 == 0, ROAD, SIDEWALK)
    labels[wall] = np.where((np.floor(p[wall, 0] / 2.5) + np.floor(p[wall, 1] / 2.0)) % 2 == 0,
                            BUILDING, VEGETATION)
    labels[~ok] = 255
    rng = np.where(labels == SKY, np.nan, t).astype(np.float32)
    return labels.reshape(camera.height, camera.width), rng.reshape(camera.height, camera.width)


@pytest.fixture(scope="module")
def camera() -> CameraModel:
    return CameraModel.from_fov(960, 600, 80.0)


def turned(deg_pan: float, deg_tilt: float = 0.0) -> np.ndarray:
    return cv2.Rodrigues(np.radians([deg_tilt, deg_pan, 0.0]).reshape(3, 1))[0]


@pytest.mark.parametrize("pan, shift", [(0.3, 0.05), (-0.2, 0.0), (0.0, 0.08)])
def test_the_motion_is_recovered_turn_and_shift_apart(camera, pan, shift):
    labels, rng = cast(camera, np.eye(3), np.zeros(3))
    rotation, translation = turned(pan, 0.1), np.array([shift, 0.0, 0.0])
    moved, _ = cast(camera, rotation, translation)
    m = estimate_motion(ReferenceView(labels, rng), moved, camera)
    true_angle = math.degrees(np.linalg.norm(cv2.Rodrigues(rotation)[0]))
    # a turn and a sideways shift trade against each other within the labels' half-pixel
    # steps: measured here 0.03 deg / 1.8 cm at most, the drift watch's target is 30 % / 3 cm
    assert abs(m.angle_deg - true_angle) < 0.05, (m.angle_deg, true_angle)
    assert np.linalg.norm(m.translation - translation) < 0.025, m.translation
    assert m.cost_after < 0.2 * m.cost_before


def test_no_motion_is_exactly_none(camera):
    labels, rng = cast(camera, np.eye(3), np.zeros(3))
    m = estimate_motion(ReferenceView(labels, rng), labels, camera)
    assert m.angle_deg == 0.0 and m.distance_m == 0.0 and m.cost_before < 1e-12


def test_label_noise_that_does_not_move_gives_a_motion_within_its_uncertainty(camera):
    """Blobs of wrong classes in the new image only (a segmenter's errors): the estimate may
    wander, but not out of its own +-, which is what the drift watch tests."""
    labels, rng = cast(camera, np.eye(3), np.zeros(3))
    noisy = labels.copy()
    gen = np.random.default_rng(3)
    for _ in range(40):
        u, v, r = gen.integers(0, 960), gen.integers(0, 600), gen.integers(5, 25)
        cv2.circle(noisy, (int(u), int(v)), int(r), int(gen.choice([ROAD, BUILDING, VEGETATION])),
                   -1)
    m = estimate_motion(ReferenceView(labels, rng), noisy, camera)
    assert m.angle_deg <= 3 * m.angle_sigma_deg or m.angle_deg < 0.02, m
    assert m.distance_m <= 3 * m.distance_sigma_m or m.distance_m < 0.01, m


def test_a_reference_with_nothing_to_align_is_refused(camera):
    flat = np.full((600, 960), ROAD, np.uint8)
    with pytest.raises(ValueError, match="boundary pixels"):
        estimate_motion(ReferenceView(flat, np.full(flat.shape, 10.0, np.float32)), flat,
                        camera)
