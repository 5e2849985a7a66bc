"""The drift check's decision margins (issue 40 item 4): how far each figure the decision reads
lies from its threshold, per catalogue layout, for an unchanged camera and for a knocked one.

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/drift_margins.py [--out DIR]
    SEMCAL_PERTURB=order,jitter=1e-6 .venv/bin/python benchmarks/drift_margins.py ...

Per layout (seed 0, small) and label variant (ideal; noisy_labels), against the scene's true pose:
* ``absolute``: ``semcal check`` without a reference on the scene's own labels: the coarse
  screen's gain (threshold ``min_gain_absolute``), the full-resolution gain of the sized pose
  (``min_gain_full``) and where the sizing ended;
* ``same``: the reference check (sized, as the monitor's first check) and then the same image
  counted from it (must be exactly 0 drift);
* ``fresh``: noisy_labels only, a fresh noise realisation at the true pose, from the reference;
* ``knock``: the demo's knock (0.3 deg pan, 5 cm sideways), from the reference: the level and
  the size against the knock's (the target: within 30 % in rotation and 3 cm in translation).
A decision whose figure lies within a few points of its threshold flips between machines.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_drift import KINDS, OPTIONS, VARIANTS, scene  # noqa: E402

from semcal_ros.engine.drift import DriftChecker, DriftParams  # noqa: E402
from semcal_ros.engine.drift_watch import DriftWatch  # noqa: E402
from semcal_ros.engine.params import CalibrationParams  # noqa: E402
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error  # noqa: E402
from semcal_ros.io import files, ply  # noqa: E402
from semcal_tools.live_demo import KNOCK_DEG, KNOCK_M, knocked  # noqa: E402
from semcal_tools.scenes.generate import camera_view, scene_world  # noqa: E402


def offset(report, truth: Pose) -> str:
    if report.estimated is None:
        return "no estimate"
    at = report.estimated
    return (f"ended {translation_error(at, truth) * 100:.1f} cm / "
            f"{rotation_error_deg(at, truth):.3f} deg from the truth")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/semcal-drift-margins", help="scene cache folder")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--loss", default="", help="engine loss kind (default: the engine's)")
    args = ap.parse_args()
    dp = DriftParams()
    engine = CalibrationParams()
    if args.loss:
        engine = replace(engine, loss=replace(engine.loss, kind=args.loss))
    print(f"loss: {engine.loss.kind}")
    print(f"SEMCAL_PERTURB={os.environ.get('SEMCAL_PERTURB', '')!r} "
          f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', '')!r} "
          f"NPY_DISABLE_CPU_FEATURES={os.environ.get('NPY_DISABLE_CPU_FEATURES', '')!r}")
    print(f"thresholds: min_gain_absolute {dp.min_gain_absolute}, min_gain {dp.min_gain}, "
          f"min_gain_full {dp.min_gain_full}; warn {dp.warn_translation_m * 100:.0f} cm / "
          f"{dp.warn_rotation_deg} deg")
    print(f"load: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}",
          flush=True)
    for kind in args.kinds.split(","):
        for variant in args.variants.split(","):
            folder = scene(Path(args.out), kind, variant)
            cloud = ply.read_ply(folder / "map.ply")
            camera = files.read_camera_info(folder / "camera_info.yaml")
            truth = files.read_pose(folder / "ground_truth.yaml")
            labels = files.read_label_image(folder / "labels.png")
            checker = DriftChecker(cloud, camera, truth, engine=engine, drift=dp)
            head = f"{kind:10s} {variant:12s}"
            a = checker.check(labels)
            print(f"{head} absolute: {a.level:5s} coarse gain {a.raw_gain * 100:5.1f} %, full "
                  f"gain {a.full_gain * 100:5.1f} %, {offset(a, truth)}; "
                  f"{a.evaluations} renders {a.seconds:.2f} s", flush=True)
            watch = DriftWatch(confirm=1)
            ref = watch.check(checker, labels)
            same = watch.check(checker, labels).report
            taken = offset(watch.reference, truth) if watch.reference else "not taken"
            print(f"{head} reference: {ref.report.level} ({taken}); "
                  f"same image from it: {same.level} {same.drift_translation_m * 100:.1f} cm "
                  f"{same.evaluations} evaluations {same.seconds:.2f} s", flush=True)
            world = scene_world(kind, 0, variant, OPTIONS)
            if variant == "noisy_labels":
                for i in range(3):
                    view = camera_view(kind, 0, variant, OPTIONS, truth, 1000 + i, world)
                    r = watch.check(checker, view).report
                    print(f"{head} fresh {i}: {r.level:5s} {r.message}; {r.evaluations} "
                          f"evaluations {r.seconds:.2f} s", flush=True)
            moved = knocked(truth)
            view = camera_view(kind, 0, variant, OPTIONS, moved,
                               "scene" if variant == "noisy_labels" else None, world)
            r = watch.check(checker, view).report
            est = r.estimated
            off = (f"{translation_error(est, moved) * 100:.1f} cm / "
                   f"{rotation_error_deg(est, moved):.3f} deg off the knocked pose"
                   if est is not None else "")
            print(f"{head} knock: {r.level:5s} sized {r.drift_translation_m * 100:.1f} cm / "
                  f"{r.drift_rotation_deg:.3f} deg (knock {KNOCK_M * 100:.0f} cm / {KNOCK_DEG} "
                  f"deg), {off}; {r.message}; {r.evaluations} evaluations {r.seconds:.2f} s",
                  flush=True)


if __name__ == "__main__":
    main()
