"""Loss variants x label-noise models on a scene (docs/quality.md): per start, the error, the loss
and the quality report, one JSON line each.
Usage: python benchmarks/label_noise_study.py SCENE --noise network --losses l2,l2b4 --runs 3 --out R.jsonl
(l2b4 = band 4 px, l2o9 = outlier width 9 px, huber... as for l2)."""

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
import numpy as np
from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
from semcal_ros.io.ply import read_ply
from semcal_tools.protocol import ProtocolParams, initial_guesses
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.search import solve
from semcal_ros.engine.pose import translation_error, rotation_error_deg
from semcal_tools.scenes.labelnoise import add_label_noise, add_network_noise, NOISE_MODELS

ap = argparse.ArgumentParser()
ap.add_argument("scene")
ap.add_argument("--noise", default="none")
ap.add_argument("--losses", default="l2")  # comma list: l2, huber, l2b4 (band 4)...
ap.add_argument("--runs", type=int, default=3)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--noise-seed", type=int, default=1)
ap.add_argument("--out", required=True)
ap.add_argument("--config")
a = ap.parse_args()
folder = Path(a.scene)
cloud = read_ply(folder / "map.ply")
target = read_label_image(folder / "labels.png")
camera = read_camera_info(folder / "camera_info.yaml")
truth = read_pose(folder / "ground_truth.yaml")
rng = np.random.default_rng(a.noise_seed)
if a.noise == "legacy":
    target = add_label_noise(target, rng)
elif a.noise in NOISE_MODELS:
    target = add_network_noise(target, rng, NOISE_MODELS[a.noise])
base = CalibrationParams.from_file(a.config) if a.config else CalibrationParams()
starts = initial_guesses(truth, ProtocolParams(runs=a.runs, keep=a.runs, seed=a.seed))
center = np.mean([s.translation for s in starts], axis=0)
for spec in a.losses.split(","):
    kind = "huber" if spec.startswith("huber") else "l2"
    core, _, ow = spec.partition("o")
    band = float(core.split("b")[-1]) if "b" in core.replace("huber", "") else 0.0
    params = replace(
        base,
        loss=replace(base.loss, kind=kind, boundary_band_px=band, outlier_width_px=float(ow) if ow else 0.0),
    )
    problem = Problem(cloud, target, camera, center, params)
    truth_loss = problem.loss(truth)
    for i, s in enumerate(starts):
        t0 = time.perf_counter()
        try:
            r = solve(problem, s, seed=a.seed + i)
            rec = dict(
                t=translation_error(r.pose, truth),
                r=rotation_error_deg(r.pose, truth),
                loss=r.loss,
                q=r.quality.to_dict(),
                dxyz=(r.pose.translation - truth.translation).tolist(),
                drpy=(r.pose.body_rpy_deg() - truth.body_rpy_deg()).tolist(),
                qe=r.quality.evaluations,
            )
        except ValueError as e:
            rec = dict(t=translation_error(s, truth), r=rotation_error_deg(s, truth), error=str(e))
        rec.update(
            scene=folder.name,
            noise=a.noise,
            loss_spec=spec,
            start=i,
            sec=time.perf_counter() - t0,
            truth_loss=truth_loss,
            load=float(open("/proc/loadavg").read().split()[0]),
        )
        with open(a.out, "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(
            spec,
            i,
            f"{rec['t'] * 100:.1f} cm {rec['r']:.3f} deg {rec.get('q', {}).get('verdict')} {rec['sec']:.1f}s",
            flush=True,
        )
