"""Compile the package's numba kernels once, at install time (``python -m semcal_tools.precompile``).

numba keeps the machine code of every ``cache=True`` kernel in ``__pycache__`` beside its source
and reuses it in every later process, until the source changes. With an empty cache the first
calibration of a fresh install compiles first: a one-start calibration test took 24.9 s with an
empty cache and 10.0 s with a filled one (2 cores, idle), and every node started before the cache
is written pays it again. ``.ci/setup.d/20-precompile.sh`` runs this after ``pip install``, so
the roadside unit's first goal, the demo and the test suite start from compiled kernels.

It drives the public paths with tiny inputs, so that numba compiles the same type signatures
the real inputs reach: the renderer and the losses at every stage for the three lens models, the
segmenters' decoders, the map builder's voxel grid, the geometric point labeller's features and
forest (its per-point pass and the cloud segmenter's range-image kernels still compile on
first use). Nothing is written but numba's cache.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.loss import LOSS_KINDS
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.render.fast import render
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world_of_size


def compile_engine() -> None:
    """Every stage's render and loss, for each lens model and each loss kind."""
    world = street_world_of_size(20_000)
    base = CalibrationParams()
    lenses = (camera(240, 150), CameraModel.fisheye_fov(240, 150),
              CameraModel.rational_fov(240, 150))
    for cam in lenses:
        rng = np.random.default_rng(0)
        # any label image will do: the kernels' types, not the picture, decide what compiles
        target = rng.choice(np.array([0, 1, 2, 8, 10], np.uint8), size=(cam.height, cam.width))
        probabilities = rng.random((*target.shape, 19), dtype=np.float32)
        probabilities /= probabilities.sum(axis=2, keepdims=True)
        for kind in LOSS_KINDS:
            for uncovered in (0.0, 0.3):
                params = replace(base, loss=replace(base.loss, kind=kind,
                                                    uncovered_cost=uncovered))
                for probs in (None, probabilities):
                    problem = Problem(world, target, cam, GROUND_TRUTH.translation, params,
                                      probabilities=probs)
                    for stage in range(len(problem.stages)):
                        problem.loss(GROUND_TRUTH, stage)
                        # the render on the calling thread (engine/workers.py)
                        render(problem.pmap, problem.level(stage).setup.view(GROUND_TRUTH), 1)


def compile_segmentation() -> None:
    """The image segmenters' argmax and softmax over the model's classes."""
    from semcal_ros.segmentation.decode import labels_from_logits
    from semcal_ros.segmentation.probabilities import probabilities_from_logits

    logits = np.random.default_rng(0).normal(size=(1, 20, 8, 12)).astype(np.float32)
    lut = np.arange(20, dtype=np.uint8)
    labels_from_logits(logits, lut)
    probabilities_from_logits(logits, lut, (16, 24))


def compile_mapping() -> None:
    """The map builder's voxel grid (with and without labels, float32 and float64 points)."""
    from semcal_ros.mapping.filters import voxel_downsample

    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        xyz = rng.uniform(-5, 5, size=(500, 3)).astype(dtype)
        label = rng.integers(0, 20, 500).astype(np.uint16)
        voxel_downsample(LabelledCloud(xyz, label), 0.5)
        voxel_downsample(LabelledCloud(xyz, None), 0.5)


def labeller_scan(n_ground: int = 3000) -> np.ndarray:
    """A tiny street for the geometric labeller: ground, a wall, a pole (x, y, z; sensor at 1.7 m
    above the ground). Shared with the test that checks this step leaves nothing to compile."""
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-20, 20, (n_ground, 2)), rng.normal(-1.7, 0.01, n_ground)]
    wall = np.c_[rng.uniform(-10, 10, 800), np.full(800, 8.0), rng.uniform(-1.7, 4, 800)]
    pole = np.c_[np.full(200, 4.0), np.full(200, -3.0), rng.uniform(-1.7, 3, 200)]
    return np.vstack([ground, wall, pole]) + rng.normal(0, 0.01, (n_ground + 1000, 3))


def compile_labeller() -> None:
    """The geometric point labeller (eigen features, the forest's re-layout and walk, the
    sparse lidar's road bridge), with the types a float32 and a float64 scan reach."""
    from semcal_ros.segmentation.geometric import SPARSE_LIDAR, GeometricParams, label_scan

    xyz = labeller_scan()
    for dtype in (np.float32, np.float64):
        for params in (GeometricParams(), GeometricParams(**SPARSE_LIDAR)):
            label_scan(xyz.astype(dtype), np.ones(len(xyz), dtype), params)


def main() -> None:
    for name, step in (("engine", compile_engine), ("segmentation", compile_segmentation),
                       ("mapping", compile_mapping), ("point labeller", compile_labeller)):
        t0 = time.perf_counter()
        step()
        print(f"precompile: {name} kernels ready ({time.perf_counter() - t0:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
