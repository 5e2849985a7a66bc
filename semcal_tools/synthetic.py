"""A labelled street sampled as points on surfaces: the engine's own test and benchmark world.

It needs no ray casting, so it is built in a second and scales to any point count (benchmarks
of 100k-3M points). Surfaces are sampled on jittered grids (like a voxel-downsampled lidar map).
The target image is
rendered from a second, denser sampling of the same surfaces at a known pose, so the map the
calibrator sees and the target share no points: a calibration must return the pose up to what the
sampling allows. A test of the engine, not of realism (semcal_tools.scenes ray-casts meshes for that).
"""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import KITTI_ID, SKY
from semcal_ros.engine.render.view import RenderParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.render import prepare_map, view_for
from semcal_ros.engine.render.reference import render


def _grid(rng, a0, a1, b0, b1, step):
    a = np.arange(a0, a1, step)
    b = np.arange(b0, b1, step)
    aa, bb = np.meshgrid(a, b)
    aa = aa.ravel() + rng.uniform(0, step, aa.size)
    bb = bb.ravel() + rng.uniform(0, step, bb.size)
    return aa, bb


def _plane(rng, step, x0, x1, y0, y1, z=0.0):
    x, y = _grid(rng, x0, x1, y0, y1, step)
    return np.c_[x, y, np.full(x.size, z)]


def _box(rng, step, x0, x1, y0, y1, h):
    """Four walls of a building."""
    walls = []
    for (a, b, fixed, along_x) in ((x0, x1, y0, True), (x0, x1, y1, True),
                                   (y0, y1, x0, False), (y0, y1, x1, False)):
        s, z = _grid(rng, a, b, 0, h, step)
        walls.append(np.c_[s, np.full(s.size, fixed), z] if along_x else np.c_[np.full(s.size, fixed), s, z])
    return np.vstack(walls)


def _cylinder(rng, step, cx, cy, r, z0, z1):
    a, z = _grid(rng, 0, 2 * np.pi * r, z0, z1, step)
    a = a / r
    return np.c_[cx + r * np.cos(a), cy + r * np.sin(a), z]


def _sphere(rng, step, c, r):
    n = int(4 * np.pi * r * r / step**2)
    p = rng.normal(size=(n, 3))
    return c + r * p / np.linalg.norm(p, axis=1, keepdims=True)


def street_world(step: float = 0.1, seed: int = 0, layout_seed: int = 7) -> LabelledCloud:
    """~0.55 M points at 10 cm; ``seed`` changes the sampling, ``layout_seed`` the street."""
    rng = np.random.default_rng(seed)
    lay = np.random.default_rng(layout_seed)
    parts: list[tuple[np.ndarray, str]] = [
        (_plane(rng, step, -40, 40, -4, -0.1), "road"),
        (_plane(rng, step, -40, 40, 0.1, 4), "road"),
        (_plane(rng, step, -40, 40, -0.1, 0.1, 0.0), "lane-marking"),
        (_plane(rng, step, -40, 40, 4, 7, 0.12), "sidewalk"),
        (_plane(rng, step, -40, 40, -7, -4, 0.12), "sidewalk"),
        (_plane(rng, step, -40, 40, -18, -7, 0.0), "terrain"),
        (_plane(rng, step, -40, 40, 7, 12, 0.0), "terrain"),
        (_box(rng, step, -40, 40, -18.05, -18, 1.5)[:, :], "fence"),
        (_box(rng, step, 3, 7.5, -2.9, -1.1, 1.5), "car"),  # dynamic: removed by the tool
    ]
    x = -40.0
    while x < 34:  # irregular frontage: a periodic street would alias along the road
        width, depth, h = lay.uniform(6, 16), lay.uniform(5, 10), lay.uniform(4, 14)
        y0 = lay.uniform(12, 14)
        parts.append((_box(rng, step, x, x + width, y0, y0 + depth, h), "building"))
        x += width + lay.uniform(2, 8)
    for px in np.cumsum(lay.uniform(8, 20, 6)) - 38:
        parts.append((_cylinder(rng, step / 2, px, 7.5, 0.12, 0, 6), "pole"))
        parts.append((_plane(rng, step / 2, px - 0.4, px + 0.4, 7.1, 7.9, 5.0), "traffic-sign"))
    for tx in np.cumsum(lay.uniform(6, 14, 7)) - 38:
        parts.append((_cylinder(rng, step / 2, tx, -10, 0.25, 0, 3), "trunk"))
        parts.append((_sphere(rng, step, np.array([tx, -10, 5.0]), 2.5), "vegetation"))
    xyz = np.vstack([p for p, _ in parts])
    label = np.concatenate([np.full(len(p), KITTI_ID[n], np.uint16) for p, n in parts])
    return LabelledCloud(xyz, label)


def street_world_of_size(n_points: int, seed: int = 0) -> LabelledCloud:
    """A street of about ``n_points`` points (the sampling step follows from the count)."""
    return street_world(step=0.1 * float(np.sqrt(560_000 / n_points)), seed=seed)


def camera(width: int = 960, height: int = 600) -> CameraModel:
    """The scenes' camera (90 deg horizontal field of view) with a little barrel distortion, so
    the engine's tests and benchmarks exercise the distortion path."""
    return CameraModel.from_fov(width, height, 90.0, (-0.05, 0.01, 0.0, 0.0, 0.0))


GROUND_TRUTH = Pose.from_body_rpy_deg([-5.0, 10.0, 7.0], [0.0, 25.0, -55.0])
#: A start about 2.6 m and 5 deg off the truth, inside the default search bounds.
PERTURBED_START = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [1.8, -1.5, 1.2],
                                         GROUND_TRUTH.body_rpy_deg() + [0.0, -3.5, 4.0])


def target_image(cam: CameraModel, pose: Pose = GROUND_TRUTH,
                 world: LabelledCloud | None = None) -> np.ndarray:
    """Cityscapes trainId image of the street at ``pose`` (sky where nothing is rendered).

    Without ``world``: from a dense sampling that shares no point with :func:`street_world`
    (realistic: the loss minimum is only as sharp as the sampling allows). With ``world``: that
    cloud rendered as the calibrator renders it, so the loss is exactly zero at ``pose`` (a test
    of the optimiser alone)."""
    if world is None:  # a fixed, dense picture: every point drawn, nothing cropped
        cloud = street_world(step=0.04, seed=99)
        rp = RenderParams(splat_lambda=20.0, radius_max=6.0, depth_falloff=0.3, lod_radius=0.0,
                          near=0.3, far=200.0, crop_radius=0.0)
    else:
        cloud, rp = world, RenderParams()
    pmap = prepare_map(cloud, center=pose.translation, radius=rp.crop_radius or None)
    labels = render(pmap, view_for(cam, pose, pmap, rp))
    labels[labels == 255] = SKY
    return labels
