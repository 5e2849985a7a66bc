"""Recompute the quality report at stored results (label_noise_study.py lines) with several settings:
does the per-axis uncertainty cover
the true error? Usage: SCENES=DIR python benchmarks/quality_recheck.py OUT.jsonl RESULTS.jsonl ...
(only the default loss's results, l2b4)"""

import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
import numpy as np
from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
from semcal_ros.io.ply import read_ply
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.quality import assess, QualityParams
from semcal_tools.scenes.labelnoise import noisy_labels

VARIANTS = {"r05": QualityParams(), "r10": QualityParams(rise=0.10), "r05h": QualityParams(stage=1)}
recs = [json.loads(l) for f in sys.argv[2:] for l in open(f)]
out = open(sys.argv[1], "a")
cache = {}
for rec in recs:
    if "error" in rec or rec["loss_spec"] != "l2b4":
        continue
    key = (rec["scene"], rec["noise"], rec["loss_spec"])
    if key not in cache:
        cache.clear()
        folder = (
            Path(os.environ.get("SCENES", "scenes")) / rec["scene"]
        )  # semcal scene --catalogue NAME --out scenes/NAME
        target = read_label_image(folder / "labels.png")
        if rec["noise"] != "none":
            target = noisy_labels(target, rec["noise"], 1)
        spec = rec["loss_spec"]
        band = float(spec.split("b")[-1]) if "b" in spec.replace("huber", "") else 0.0
        base = CalibrationParams()
        params = replace(
            base,
            loss=replace(
                base.loss, kind="huber" if spec.startswith("huber") else "l2", boundary_band_px=band
            ),
        )
        truth = read_pose(folder / "ground_truth.yaml")
        cache[key] = (
            Problem(
                read_ply(folder / "map.ply"),
                target,
                read_camera_info(folder / "camera_info.yaml"),
                truth.translation,
                params,
            ),
            truth,
        )
    problem, truth = cache[key]
    pose = Pose.from_body_rpy_deg(
        truth.translation + np.array(rec["dxyz"]), truth.body_rpy_deg() + np.array(rec["drpy"])
    )
    res = dict(
        scene=rec["scene"],
        noise=rec["noise"],
        loss_spec=rec["loss_spec"],
        t=rec["t"],
        r=rec["r"],
        dxyz=rec["dxyz"],
        drpy=rec["drpy"],
    )
    for name, qp in VARIANTS.items():
        t0 = time.perf_counter()
        q = assess(problem, pose, (), qp)
        res[name] = dict(
            ut=q.uncertainty_translation_m,
            ur=q.uncertainty_rpy_deg,
            v=q.verdict,
            sec=time.perf_counter() - t0,
            n=q.evaluations,
            agr=q.agreement,
        )
    out.write(json.dumps(res) + "\n")
    out.flush()
    print(rec["scene"], rec["noise"], rec["loss_spec"], flush=True)
