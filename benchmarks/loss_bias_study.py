"""Where the loss minimum sits with ideal labels: the loss along each axis around the true pose.

Issue 18 item 2. For each scene (ideal labels) and each setting (the defaults, then one default at a
time switched to the paper's), the loss is sampled along the six axes of the body frame (x forward,
y left, z up; roll, pitch, yaw) at and around the truth, and a table is printed: per axis the
sampled argmin and the vertex of a parabola fitted to the samples (both cm or deg, 0 = unbiased),
and the parabola's curvature (loss per cm^2 / deg^2: how sharply the axis is held).

It calls only ``Problem.loss(pose, stage)`` (one render + one loss each): no searches.

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/loss_bias_study.py \
        --scenes /tmp/lbias/junction [...] [--settings default,no_falloff,...] [--stages -1]

``--stages``: schedule stages to sample (-1 full resolution, 0 = 1/4, 1 = 1/2 by default).
``--principal``: also sample the loss against a shift of the principal point (+-1 px): a
half-pixel convention error between the scene's camera and the renderer shows as a minimum
away from 0 there.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
from semcal_ros.io.ply import read_ply
from semcal_ros.engine.labels import INVALID, SKY
from semcal_ros.mapping.filters import voxel_downsample
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import BODY_FROM_OPTICAL, Pose
from semcal_ros.engine.problem import Problem

AXES = ("x", "y", "z", "roll", "pitch", "yaw")
#: the authors' code: radius 0.195 NDC units / distance at 480x300 (NDC spans the short side):
#: 0.195 * 300 / 2 px at half resolution = 58.5 px x m at full resolution
PAPER_LAMBDA = 0.195 * 600 / 2.0


def _with(params: CalibrationParams, **groups: dict) -> CalibrationParams:
    return replace(params, **{g: replace(getattr(params, g), **v) for g, v in groups.items()})


D = CalibrationParams()
#: name -> (params, target transform, map voxel m or 0). One default at a time to the paper's.
SETTINGS = {
    "default": (D, None, 0.0),
    "lambda_paper": (_with(D, render={"splat_lambda": PAPER_LAMBDA}), None, 0.0),
    "no_falloff": (_with(D, render={"depth_falloff": 0.0, "depth_falloff_coarse": 0.0}), None, 0.0),
    "no_lod": (_with(D, render={"lod_radius": 0.0}), None, 0.0),
    "no_band": (_with(D, loss={"boundary_band_px": 0.0}), None, 0.0),
    "uncovered_0.3": (_with(D, loss={"uncovered_cost": 0.3}), None, 0.0),
    "crop_75m": (_with(D, render={"crop_radius": 75.0}), None, 0.0),
    "sky_masked": (D, "sky_masked", 0.0),
    "voxel_10cm": (D, None, 0.10),
    "radius_max_16": (_with(D, render={"radius_max": 16.0}), None, 0.0),
    "l2_band": (_with(D, loss={"kind": "l2"}), None, 0.0),
    "lik_reestimated": (_with(D, loss={"kind": "likelihood", "em": False}), None, 0.0),
    "lik_em_ep100": (_with(D, loss={"kind": "likelihood", "em": True, "em_prior_pixels": 100.0}),
                     None, 0.0),
    "lik_em_ep100_noband": (_with(D, loss={"kind": "likelihood", "em": True,
                                           "em_prior_pixels": 100.0, "boundary_band_px": 0.0}),
                            None, 0.0),
    "paper_render": (_with(D, render={"splat_lambda": PAPER_LAMBDA, "depth_falloff": 0.0,
                                      "depth_falloff_coarse": 0.0, "lod_radius": 0.0},
                           loss={"boundary_band_px": 0.0}), None, 0.0),
}


def offsets(step_cm: float, step_deg: float, n: int) -> dict[str, np.ndarray]:
    k = np.arange(-n, n + 1)
    return {a: k * (step_cm if i < 3 else step_deg) for i, a in enumerate(AXES)}


def moved(truth: Pose, axis: str, amount: float) -> Pose:
    """``truth`` moved by ``amount`` cm along a body axis, or turned by ``amount`` deg."""
    i = AXES.index(axis)
    if i < 3:
        body = truth.rotation @ BODY_FROM_OPTICAL.T  # columns: forward, left, up in the map
        return Pose(truth.translation + body[:, i] * amount / 100.0, truth.quaternion)
    rpy = truth.body_rpy_deg()
    rpy[i - 3] += amount
    return Pose.from_body_rpy_deg(truth.translation, rpy)


def fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """(sampled argmin, parabola vertex, curvature 2a, scatter) of the samples; the vertex is
    clipped to the sampled range (a parabola open downwards or flat says: no minimum inside).
    ``scatter`` = sqrt(2 s / 2a), s the RMS residual of the fit: how far the loss's pixel noise
    alone can move a minimum (a vertex within it is not a bias)."""
    a, b, c = np.polyfit(x, y, 2)
    vertex = float(np.clip(-b / (2 * a), x[0], x[-1])) if a > 0 else float("nan")
    lo = np.flatnonzero(y == y.min())
    resid = float(np.sqrt(np.mean((np.polyval((a, b, c), x) - y) ** 2)))
    scatter = float(np.sqrt(2 * resid / (2 * a))) if a > 0 else float("nan")
    return float(np.mean(x[lo])), vertex, float(2 * a), scatter


JOINT_AXES = ("x", "y", "z", "pitch", "yaw")  # the search's parameters (roll fixed)


def pose_at(truth: Pose, delta: np.ndarray) -> Pose:
    """``truth`` moved by x, y, z (cm, body axes) and turned by pitch, yaw (deg)."""
    body = truth.rotation @ BODY_FROM_OPTICAL.T
    rpy = truth.body_rpy_deg()
    rpy[1:] += delta[3:]
    return Pose.from_body_rpy_deg(truth.translation + body @ delta[:3] / 100.0, rpy)


def joint_fit(problem: Problem, truth: Pose, stage: int, n: int, half_cm: float,
              half_deg: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A quadratic fitted to the loss at ``n`` poses drawn in a box round the truth over the
    search's five parameters: (vertex cm/deg, eigenvalues, eigenvectors) in units where 1 cm and
    ``half_deg / half_cm`` deg weigh alike. One-axis scans miss a valley along a combination
    (forward + pitch keeps far points in place); the fitted vertex does not."""
    scale = np.array([half_cm] * 3 + [half_deg] * 2)
    u = rng.uniform(-1.0, 1.0, (n, 5))
    ys = np.array([problem.loss(pose_at(truth, row * scale), stage) for row in u])
    iu = np.triu_indices(5)
    quad = np.einsum("ni,nj->nij", u, u)[:, iu[0], iu[1]]
    design = np.hstack([np.ones((n, 1)), u, quad])
    coef, *_ = np.linalg.lstsq(design, ys, rcond=None)
    g = coef[1:6]
    h = np.zeros((5, 5))
    h[iu] = coef[6:]
    h = h + h.T  # off-diagonal c_ij x_i x_j -> H_ij = c_ij; diagonal c_ii x_i^2 -> H_ii = 2 c_ii
    vertex = np.linalg.solve(h, -g)
    w, v = np.linalg.eigh(h)
    return vertex * scale, w / half_cm ** 2, v


def principal_shift(problem: Problem, target: np.ndarray, camera: CameraModel, truth: Pose,
                    stage: int, steps: np.ndarray) -> dict[str, np.ndarray]:
    """Loss at the truth with the renderer's principal point shifted by ``steps`` px (u, v)."""
    out = {}
    for j, name in enumerate(("cx", "cy")):
        losses = []
        for s in steps:
            k = camera.k.copy()
            k[j, 2] += s
            cam = replace(camera, k=k)
            p = Problem(None, target, cam, truth.translation,
                        problem.params, prepared=problem.pmap)
            losses.append(p.loss(truth, stage))
        out[name] = np.asarray(losses)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--settings", default=",".join(SETTINGS))
    ap.add_argument("--stages", default="-1", help="comma list of schedule stages, -1 = full")
    ap.add_argument("--full-only", default="", help="settings sampled at full resolution only")
    ap.add_argument("--steps", type=int, default=10, help="samples each side of the truth")
    ap.add_argument("--step-cm", type=float, default=1.0)
    ap.add_argument("--step-deg", type=float, default=0.02)
    ap.add_argument("--principal", action="store_true")
    ap.add_argument("--joint", type=int, default=0,
                    help="poses for a 5-D quadratic fit round the truth (0: none)")
    ap.add_argument("--joint-settings", default="default", help="settings that get the fit")
    ap.add_argument("--joint-cm", type=float, default=6.0)
    ap.add_argument("--joint-deg", type=float, default=0.12)
    args = ap.parse_args()
    stages = [int(s) for s in args.stages.split(",")]
    grid = offsets(args.step_cm, args.step_deg, args.steps)
    print(f"load {open('/proc/loadavg').read().split()[:3]}", flush=True)
    print("scene | setting | stage | loss@truth | per axis: argmin / vertex / curvature / "
          "scatter (x y z cm, roll pitch yaw deg; curvature per cm^2 / deg^2)")
    for folder in map(Path, args.scenes):
        truth = read_pose(folder / "ground_truth.yaml")
        camera = read_camera_info(folder / "camera_info.yaml")
        labels = read_label_image(folder / "labels.png")
        cloud = read_ply(folder / "map.ply")
        shared = {}
        for name in args.settings.split(","):
            params, target_rule, voxel = SETTINGS[name]
            target = labels
            if target_rule == "sky_masked":
                target = np.where(labels == SKY, INVALID, labels).astype(np.uint8)
            t0 = time.perf_counter()
            key = (params.render.crop_radius, voxel)
            if key not in shared:
                c = cloud if not voxel else voxel_downsample(cloud.select(np.ones(len(cloud), bool)),
                                                             voxel)
                shared[key] = Problem(c, labels, camera, truth.translation, params).pmap
            problem = Problem(None, target, camera, truth.translation, params,
                              prepared=shared[key])
            if params.loss.em:  # an EM loss: its E step at the truth (is the truth its fixed point?)
                problem.freeze(truth)
            for stage in (stages if name not in args.full_only.split(",") else [-1]):
                at = problem.loss(truth, stage)
                cells = []
                for axis in AXES:
                    xs = grid[axis]
                    ys = np.array([problem.loss(moved(truth, axis, float(v)), stage) for v in xs])
                    amin, vertex, curv, scatter = fit(xs, ys)
                    cells.append(f"{amin:+.2f}/{vertex:+.2f}/{curv:.1e}/{scatter:.2f}")
                print(f"{folder.name} | {name} | {problem.stages[stage].scale} | {at:.5f} | "
                      + " | ".join(cells) + f" | {time.perf_counter() - t0:.0f} s", flush=True)
                if args.joint and name in args.joint_settings.split(","):
                    vertex, w, v = joint_fit(problem, truth, stage, args.joint, args.joint_cm,
                                             args.joint_deg, np.random.default_rng(0))
                    weak = v[:, 0] * np.sign(v[np.argmax(np.abs(v[:, 0])), 0])
                    print(f"    joint vertex x y z cm {np.round(vertex[:3], 2).tolist()} pitch yaw "
                          f"deg {np.round(vertex[3:], 3).tolist()}; eigenvalues (per cm^2) "
                          f"{np.array2string(w, precision=1)}; weakest direction "
                          f"{np.round(weak, 2).tolist()}", flush=True)
                    # the loss along that direction (t in units of the fit's box)
                    ts = np.linspace(-1.5, 1.5, 13)
                    scale = np.array([args.joint_cm] * 3 + [args.joint_deg] * 2)
                    along = [problem.loss(pose_at(truth, t * weak * scale), stage) for t in ts]
                    best = ts[int(np.argmin(along))] * weak * scale
                    print(f"    along it: lowest at x y z cm {np.round(best[:3], 1).tolist()} "
                          f"pitch yaw deg {np.round(best[3:], 3).tolist()}, loss "
                          f"{min(along):.6f} vs {along[6]:.6f} at the truth; losses "
                          f"{np.round(along, 6).tolist()}", flush=True)
                if args.principal:
                    steps = np.linspace(-1.0, 1.0, 9)
                    sh = principal_shift(problem, target, camera, truth, stage, steps)
                    for k, ys in sh.items():
                        print(f"    principal {k} shift px {steps.round(2).tolist()}: "
                              f"argmin {steps[np.argmin(ys)]:+.2f} px, losses "
                              f"{np.round(ys, 5).tolist()}", flush=True)
    print(f"load {open('/proc/loadavg').read().split()[:3]}", flush=True)


if __name__ == "__main__":
    main()
