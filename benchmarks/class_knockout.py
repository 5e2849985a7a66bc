"""Which class makes a wrong result beat the truth? For each single-frame run of an
``evidence_study.py`` file that ended more than ``--min-cm`` off and was not failed, the
full-resolution loss (``Problem.loss``) at the truth and at the run's result, with every map class
in turn left out (its points dropped) and every image class in turn left out (its pixels
INVALID). A class whose absence lets the truth win is one the wrong result rests on; when none
does, the result follows what is left of the labels as a whole (docs/engine.md, "Why ours1 ends
61-91 cm off").

    .venv/bin/python benchmarks/class_knockout.py /work/scenes RUNS.jsonl [--only pjlab_ours1]

Scene folders: ``benchmarks/make_real_scenes.sh``; runs: ``benchmarks/evidence_study.py run``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from multiframe_study import load_frame, paper_starts  # noqa: E402

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", type=Path)
    ap.add_argument("runs", type=Path)
    ap.add_argument("--only", default="", help="only sets whose name holds this")
    ap.add_argument("--min-cm", type=float, default=40.0)
    ap.add_argument("--min-share", type=float, default=0.01,
                    help="classes holding less of the map / image are not tried")
    args = ap.parse_args()

    from semcal_ros.engine.labels import INVALID, KITTI_ID
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import Pose
    from semcal_ros.io import files
    from semcal_tools.protocol import initial_guesses

    kitti_names = {v: k for k, v in KITTI_ID.items()}
    base = CalibrationParams()
    for line in args.runs.read_text().splitlines():
        r = json.loads(line)
        if "error" in r or "," in r["set"] or args.only not in r["set"] \
                or r["translation_cm"] < args.min_cm or r["verdict"] == "failed":
            continue
        folder = args.scenes / r["set"]
        frame = load_frame(folder, base)
        truth = files.read_pose(folder / "ground_truth.yaml")
        start = initial_guesses(truth, paper_starts([r["start"]]))[r["start"]]
        e = np.array(r["error_axes"])
        result = Pose.from_body_rpy_deg(truth.translation + e[:3], truth.body_rpy_deg() + e[3:])

        def losses(f) -> tuple[float, float]:
            problem = f.problem(start.translation)
            return problem.loss(truth), problem.loss(result)

        at_truth, at_result = losses(frame)
        print(f"{r['set']} start {r['start']} seed {r['seed']}: {r['translation_cm']} cm, "
              f"{r['verdict']}; loss at the truth {at_truth:.4f}, at the result {at_result:.4f}")
        labels = frame.map_cloud.label
        for c in np.unique(labels):
            share = float(np.mean(labels == c))
            if share < args.min_share:
                continue
            t, s = losses(dataclasses.replace(frame, map_cloud=frame.map_cloud.select(labels != c)))
            print(f"  without map {kitti_names.get(int(c), int(c)):>12} ({share * 100:4.1f} %): "
                  f"truth {t:.4f}, result {s:.4f}{'  <- the truth wins' if t < s else ''}")
        image = frame.labels
        for c in np.unique(image):
            share = float(np.mean(image == c))
            if c == INVALID or share < args.min_share:
                continue
            masked = np.where(image == c, INVALID, image).astype(image.dtype)
            t, s = losses(dataclasses.replace(frame, labels=masked))
            print(f"  without image trainId {int(c):>3} ({share * 100:4.1f} %): truth {t:.4f}, "
                  f"result {s:.4f}{'  <- the truth wins' if t < s else ''}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
