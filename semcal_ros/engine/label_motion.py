"""How far a static camera moved between two of its label images, with the map's depth.

The drift watch's question for a calibrated camera is "has it moved since its reference image?".
Answered by registering each new image to the *map* (a search over renders), the answer inherits
the loss's bias and its coarse resolution: on the catalogue a 0.3 deg + 5 cm knock was missed on
five of eight layouts and labels, and an unchanged camera was called drifted on some CPUs
(docs/drift.md). Registered to the *reference label image* instead, the two images share every
bias of the labeller and the map, and a move of the camera is the only thing that shifts their
boundaries against each other.

The estimate is chamfer matching of class boundaries (Barrow et al. 1977; the semantic form of
direct image alignment, Lucas & Kanade 1981) in six degrees of freedom: pixels near a class
boundary of the reference are lifted to 3-D with the depth the map has there at the calibration
(the z-buffer of one full-resolution render), moved by a candidate camera motion, projected with
the camera's own lens model, and charged their distance to the nearest pixel of their class in
the new image (truncated: a pixel the labeller got wrong costs at most 1). Gauss-Newton with a
numeric Jacobian minimises the mean charge, coarse to fine (a wide truncation first, so a move of
tens of pixels is still seen, then a narrow one). The depth is what separates a turn from a shift:
5 cm sideways moves a point 10 m away by 0.29 deg and one 40 m away by 0.07 deg, a turn moves both
alike.

Its uncertainty comes from independent evidence: the same estimate on the left and on the right
half of the samples (disjoint pixels, one image); half their difference per axis is the
uncertainty, so a move is counted only when it stands out of what the labels' own noise moves.
No ROS and no renders here: :mod:`semcal_ros.engine.drift` builds the reference view and decides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.labels import INVALID, SKY

#: truncations of the charge (px, full resolution): coarse to fine
BANDS_PX = (24.0, 6.0)
#: reference pixels this close to the image border are not sampled (they leave it first)
BORDER_PX = 8
#: samples kept (every k-th boundary pixel: deterministic, the same on every machine)
MAX_SAMPLES = 24000
#: Gauss-Newton iterations per band, and the step below which it stops (parameter units)
ITERATIONS = 12
STEP_TOL = 1e-4
#: the least uncertainty per axis: 0.005 deg, 2 mm (a tenth of a pixel 10 m away)
SIGMA_FLOOR = np.array([math.radians(0.005)] * 3 + [0.002] * 3)
#: parameter units: rotations in 0.1 deg, translations in 5 cm (both move a point 10 m away by
#: a few pixels), so one damping serves every axis
UNIT = np.array([math.radians(0.1)] * 3 + [0.05] * 3)


def _rotation(rvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]


@dataclass(frozen=True)
class Motion:
    """The camera's motion from the reference to the new image, in the reference optical frame
    (x right, y down, z forward): a point X seen by the reference is seen by the new camera at
    R.T @ (X - t)."""

    rotation_vector: np.ndarray  # (3,) rad (axis x angle)
    translation: np.ndarray  # (3,) m
    rotation_sigma: np.ndarray  # (3,) rad, per axis, from the two halves
    translation_sigma: np.ndarray  # (3,) m
    cost_before: float  # mean charge (band-normalised, in [0, 1]) at no motion
    cost_after: float  # ... at the estimate
    samples: int
    evaluations: int

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) R: the new camera's axes in the reference optical frame."""
        return _rotation(self.rotation_vector)

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(self.rotation_vector)))

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.translation))

    @property
    def angle_sigma_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(self.rotation_sigma)))

    @property
    def distance_sigma_m(self) -> float:
        return float(np.linalg.norm(self.translation_sigma))

    @property
    def gain(self) -> float:
        """The share of the charge at no motion that the motion explains."""
        return (self.cost_before - self.cost_after) / self.cost_before \
            if self.cost_before > 0 else 0.0


@dataclass(frozen=True)
class ReferenceView:
    """A reference label image (aligned classes, full resolution) and the map's depth (m, along
    each pixel's ray; NaN where the map drew nothing) seen from the calibration."""

    labels: np.ndarray
    depth: np.ndarray


def boundary_samples(view: ReferenceView, camera: CameraModel, band_px: float = BANDS_PX[0],
                     max_samples: int = MAX_SAMPLES) -> tuple[np.ndarray, np.ndarray,
                                                              np.ndarray]:
    """(points (N, 3) in the reference optical frame, their classes (N,), their column (N,)):
    the reference's pixels within ``band_px`` of a class boundary that have a depth (or are sky:
    at infinity, moved by the rotation alone), every k-th of them."""
    labels = view.labels
    h, w = labels.shape
    valid = labels != INVALID
    edge = np.zeros((h, w), bool)
    edge[:, 1:] |= (labels[:, 1:] != labels[:, :-1]) & valid[:, 1:] & valid[:, :-1]
    edge[1:, :] |= (labels[1:, :] != labels[:-1, :]) & valid[1:, :] & valid[:-1, :]
    near = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3) <= band_px
    depth = view.depth
    sky = labels == SKY
    keep = near & valid & (np.isfinite(depth) | sky)
    keep[:BORDER_PX], keep[-BORDER_PX:], keep[:, :BORDER_PX], keep[:, -BORDER_PX:] = (False,) * 4
    vv, uu = np.nonzero(keep)
    step = max(1, int(math.ceil(len(vv) / max_samples)))
    vv, uu = vv[::step], uu[::step]
    rays, ok = camera.unproject(np.stack([uu, vv], axis=1).astype(np.float64))
    vv, uu, rays = vv[ok], uu[ok], rays[ok]
    d = depth[vv, uu]
    far = ~np.isfinite(d)
    # a sky pixel is a direction: placed 1e4 m out, a translation of centimetres moves it by
    # nothing the images can show
    points = rays * np.where(far, 1e4, d)[:, None]
    return points, labels[vv, uu].astype(np.uint8), uu.astype(np.float64)


class _Charge:
    """The mean truncated distance of moved samples to their class in one new image."""

    def __init__(self, labels: np.ndarray, classes: np.ndarray, band_px: float) -> None:
        self.h, self.w = labels.shape
        self.band = band_px
        self.fields = {}
        for c in np.unique(classes):
            dist = cv2.distanceTransform((labels != c).astype(np.uint8), cv2.DIST_L2, 5)
            self.fields[int(c)] = np.minimum(dist, band_px).astype(np.float32) / band_px

    def residuals(self, camera: CameraModel, points: np.ndarray, classes: np.ndarray,
                  params: np.ndarray) -> np.ndarray:
        p = params * UNIT
        moved = (points - p[3:]) @ _rotation(p[:3])  # R.T @ (X - t), row-wise
        uv, _ = camera.project(moved)
        out = np.ones(len(points))
        # a sample that leaves the image is charged where it left (clamped to the border): a
        # full charge would make every move that pushes the border's samples out look worse
        u = np.clip(uv[:, 0], 0.0, self.w - 1.0)
        v = np.clip(uv[:, 1], 0.0, self.h - 1.0)
        ok = np.isfinite(uv).all(axis=1)  # inside the image or not: clamped above
        for c, field in self.fields.items():
            sel = ok & (classes == c)
            if sel.any():
                out[sel] = _bilinear(field, u[sel], v[sel])
        return out


def _bilinear(field: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u0 = np.minimum(np.floor(u).astype(np.int64), field.shape[1] - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), field.shape[0] - 2)
    fu, fv = u - u0, v - v0
    a = field[v0, u0] * (1 - fu) + field[v0, u0 + 1] * fu
    b = field[v0 + 1, u0] * (1 - fu) + field[v0 + 1, u0 + 1] * fu
    return a * (1 - fv) + b * fv


def _gauss_newton(charge: _Charge, camera: CameraModel, points: np.ndarray,
                  classes: np.ndarray, start: np.ndarray, free: np.ndarray
                  ) -> tuple[np.ndarray, float, int]:
    """Levenberg-damped Gauss-Newton on the free parameters from ``start``: (params, mean
    charge, evaluations)."""
    x = start.copy()
    r = charge.residuals(camera, points, classes, x)
    cost = float(r.mean())
    evaluations, lam, h = 1, 1e-3, 0.05
    for _ in range(ITERATIONS):
        jac = np.zeros((len(r), len(free)))
        for k, axis in enumerate(free):
            step = x.copy()
            step[axis] += h
            jac[:, k] = (charge.residuals(camera, points, classes, step) - r) / h
        evaluations += len(free)
        a = jac.T @ jac
        g = jac.T @ r
        improved = False
        for _ in range(6):
            delta = -np.linalg.solve(a + lam * (np.diag(np.diag(a)) + 1e-9 * np.eye(len(free))),
                                     g)
            trial = x.copy()
            trial[free] += delta
            rt = charge.residuals(camera, points, classes, trial)
            evaluations += 1
            if rt.mean() < cost:
                x, r, cost, improved = trial, rt, float(rt.mean()), True
                lam = max(lam / 4, 1e-6)
                break
            lam *= 8
        if not improved or np.max(np.abs(delta)) < STEP_TOL:
            break
    return x, cost, evaluations


def estimate_motion(reference: ReferenceView, labels: np.ndarray, camera: CameraModel,
                    free_roll: bool = True) -> Motion:
    """The camera's motion from ``reference`` to the new aligned label image ``labels`` (full
    resolution; see the module docstring), with its uncertainty from the two image halves."""
    points, classes, column = boundary_samples(reference, camera)
    if len(points) < 50:
        raise ValueError(f"the reference image has {len(points)} usable boundary pixels "
                         "(< 50): nothing to align")
    free = np.array([0, 1, 2, 3, 4, 5] if free_roll else [0, 1, 3, 4, 5])
    x = np.zeros(6)
    evaluations = 0
    before = math.nan
    halves = (column < camera.width / 2, column >= camera.width / 2)
    half_x = [np.zeros(6), np.zeros(6)]
    for band in BANDS_PX:
        charge = _Charge(labels, classes, band)
        if band == BANDS_PX[-1]:
            before = float(charge.residuals(camera, points, classes, np.zeros(6)).mean())
        x, cost, n = _gauss_newton(charge, camera, points, classes, x, free)
        evaluations += n
        if band == BANDS_PX[-1]:
            for k, half in enumerate(halves):
                if half.sum() >= 50:
                    half_x[k], _, n = _gauss_newton(charge, camera, points[half],
                                                    classes[half], x, free)
                    evaluations += n
                else:  # one half shows nothing: its evidence is the whole estimate's
                    half_x[k] = x
    # half the halves' difference, never below what the samples resolve (two halves that
    # converged to the same point do not make a move of any size significant)
    sigma = np.maximum(np.abs(half_x[0] - half_x[1]) / 2.0 * UNIT, SIGMA_FLOOR)
    p = x * UNIT
    return Motion(p[:3], p[3:], sigma[:3], sigma[3:], before, cost, len(points), evaluations)


__all__ = ["BANDS_PX", "Motion", "ReferenceView", "boundary_samples", "estimate_motion"]
