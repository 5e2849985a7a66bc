"""Issue 32 item 3: do the cues beside the labels pay? The same real frames and starts, without
and with each cue at several weights.

For each scene folder (``semcal real-scene``: map.ply, labels.png, image.png, camera_info.yaml,
ground_truth.yaml, calibrator.yaml) and each setting, the engine's full default procedure
(``solve``: verification starts, quality report) runs from the paper's starts (ground truth +
uniform noise of +-2.5 m per axis, +-5 deg pitch and yaw; ``semcal_tools.protocol``, seeds as
benchmarks/real_loss_study.py), with the scene's calibrator.yaml over ``loss.kind: likelihood``.
One record per run (JSON lines, appended): error, loss, verdict, wall and CPU seconds
(``time.process_time``: the whole process, the renderer's threads included), the 1-minute load.

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/cue_study.py \
        /work/scenes/kitti00_0*_esp --settings lik,lik_e0.1,lik_e0.3 --runs 2 --out cues.jsonl
    .venv/bin/python benchmarks/cue_study.py --table cues.jsonl

Settings (comma separated): ``lik`` the likelihood loss without cues; ``_eW`` adds the depth-edge
cue with ``cues.edge_weight`` W; ``_dG`` its ``edge_decay`` G, ``_jJ`` its ``edge_min_jump`` J,
``_iI`` its ``edge_inset`` I; ``_nW`` adds the intensity-grey NID cue with
``cues.intensity_weight`` W (the scene's map.ply must carry intensity), ``_bB`` its
``intensity_bins`` B.

``--profile``: instead of calibrating, the label loss and each cue's term alone at the truth and
at shifts along each axis (full resolution), and where along each axis each is lowest:

    .venv/bin/python benchmarks/cue_study.py --profile tmp/scenes/kitti00_000000_esp
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def setting_params(name: str, base):
    """CalibrationParams of a setting name on top of ``base``."""
    kind, *mods = name.split("_")
    if kind != "lik":
        raise ValueError(f"unknown setting '{name}'")
    loss = replace(base.loss, kind="likelihood")
    cues = base.cues
    for m in mods:
        if m.startswith("e"):
            cues = replace(cues, edge_weight=float(m[1:]))
        elif m.startswith("d"):
            cues = replace(cues, edge_decay=float(m[1:]))
        elif m.startswith("j"):
            cues = replace(cues, edge_min_jump=float(m[1:]))
        elif m.startswith("i"):
            cues = replace(cues, edge_inset=float(m[1:]))
        elif m.startswith("n"):
            cues = replace(cues, intensity_weight=float(m[1:]))
        elif m.startswith("b"):
            cues = replace(cues, intensity_bins=int(m[1:]))
        else:
            raise ValueError(f"unknown modifier '{m}' in '{name}'")
    return replace(base, loss=loss, cues=cues)


def run_scene(folder: Path, settings: list[str], runs: int, seed: int, out: Path) -> None:
    import cv2

    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.engine.problem import Problem
    from semcal_ros.engine.search import solve
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply
    from semcal_tools.protocol import ProtocolParams, initial_guesses

    cloud = read_ply(folder / "map.ply")
    labels = read_label_image(folder / "labels.png")
    image = cv2.imread(str(folder / "image.png"), cv2.IMREAD_COLOR)
    camera = read_camera_info(folder / "camera_info.yaml")
    truth = read_pose(folder / "ground_truth.yaml")
    scene_cfg = folder / "calibrator.yaml"
    prepared = None
    protocol = ProtocolParams(runs=runs, keep=runs, noise_xyz_m=2.5, noise_pitch_deg=5.0,
                              noise_yaw_deg=5.0, seed=seed)
    for name in settings:
        base = CalibrationParams.from_file(scene_cfg if scene_cfg.is_file() else None)
        params = setting_params(name, base)
        c0 = time.process_time()
        problem = Problem(cloud if prepared is None else None, labels, camera, truth.translation,
                          params, prepared=prepared, image=image)
        prepare_cpu = time.process_time() - c0
        prepared = problem.pmap
        for i, start in enumerate(initial_guesses(truth, protocol)):
            rec = {"scene": folder.name, "setting": name, "run": i, "prepare_cpu": prepare_cpu}
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                res = solve(problem, start, seed=seed + i)
                q = res.quality
                rec.update(t_cm=translation_error(res.pose, truth) * 100,
                           r_deg=rotation_error_deg(res.pose, truth), loss=float(res.loss),
                           verdict=q.verdict if q else "")
            except ValueError as exc:
                rec.update(t_cm=translation_error(start, truth) * 100,
                           r_deg=rotation_error_deg(start, truth), loss=None, verdict="error",
                           reason=str(exc))
            rec["seconds"] = time.perf_counter() - t0
            rec["cpu"] = time.process_time() - c0
            rec["load"] = os.getloadavg()[0]
            with out.open("a") as f:
                f.write(json.dumps(rec) + "\n")
            print(f"{folder.name:28} {name:14} {rec['t_cm']:8.1f} cm {rec['r_deg']:6.2f} deg "
                  f"{rec['verdict']:12} {rec['seconds']:5.1f} s {rec['cpu']:5.1f} cpu "
                  f"load {rec['load']:.1f}", flush=True)


def cost(folder: Path, settings: list[str], repeats: int) -> None:
    """CPU ms per loss evaluation (one render + the loss, each stage) per setting, at poses
    around the truth: what a cue adds to every step of the search."""
    import cv2

    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import Pose
    from semcal_ros.engine.problem import Problem
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply

    cloud = read_ply(folder / "map.ply")
    labels = read_label_image(folder / "labels.png")
    image = cv2.imread(str(folder / "image.png"), cv2.IMREAD_COLOR)
    camera = read_camera_info(folder / "camera_info.yaml")
    truth = read_pose(folder / "ground_truth.yaml")
    rng = np.random.default_rng(0)
    poses = [Pose.from_vector(truth.vector() + rng.uniform(-1, 1, 6) * [0.5, 0.5, 0.5, 0, 0.01,
                                                                        0.01])
             for _ in range(repeats)]
    base = CalibrationParams.from_file(folder / "calibrator.yaml")
    for name in settings:
        c0 = time.process_time()
        problem = Problem(cloud, labels, camera, truth.translation, setting_params(name, base),
                          image=image)
        prep = time.process_time() - c0
        cells = []
        for stage in range(len(problem.stages)):
            problem.loss(poses[0], stage)  # compiled and warm
            c0 = time.process_time()
            for pose in poses:
                problem.loss(pose, stage)
            cells.append(f"1/{problem.stages[stage].scale}: "
                         f"{(time.process_time() - c0) / repeats * 1e3:.2f} ms")
        print(f"{folder.name} {name:12} prepare {prep:.2f} s CPU; per evaluation "
              + ", ".join(cells) + f" (load {os.getloadavg()[0]:.1f})", flush=True)


#: shifts of the profile: metres along x, y, z; degrees of pitch and yaw
PROFILE_STEPS_M = (-0.5, -0.25, -0.1, 0.0, 0.1, 0.25, 0.5)
PROFILE_STEPS_DEG = (-1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0)


def profile(folder: Path, out: Path | None) -> None:
    """Each term alone (label loss, edge term, NID) at the truth and at shifts along each
    axis, full resolution: its value at the truth, where along each axis it is lowest, and its
    rise from the truth to the +-0.25 m / +-0.5 deg shifts (mean of both sides)."""
    import cv2

    from semcal_ros.engine.cues import CueParams
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import Pose
    from semcal_ros.engine.problem import Problem
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply

    cloud = read_ply(folder / "map.ply")
    labels = read_label_image(folder / "labels.png")
    image = cv2.imread(str(folder / "image.png"), cv2.IMREAD_COLOR)
    camera = read_camera_info(folder / "camera_info.yaml")
    truth = read_pose(folder / "ground_truth.yaml")
    base = setting_params("lik", CalibrationParams.from_file(folder / "calibrator.yaml"))
    params = replace(base, cues=CueParams(edge_weight=1.0, intensity_weight=1.0))
    problem = Problem(cloud, labels, camera, truth.translation, params, image=image)
    level = problem.level(-1)
    cued = level.loss

    def terms(pose: Pose) -> dict[str, float]:
        rendered = problem.render(pose)
        assert problem._last is not None
        _, keys, values = problem._last
        return {"label": float(cued.labels(rendered)), "edge": cued.edge.term(keys),
                "nid": cued.intensity.term(values)}

    at = terms(truth)
    rec: dict = {"scene": folder.name, "truth": at}
    for axis, name in enumerate(("x", "y", "z", "roll", "pitch", "yaw")):
        if name == "roll":
            continue
        steps = PROFILE_STEPS_M if axis < 3 else PROFILE_STEPS_DEG
        rows = []
        for d in steps:
            v = truth.vector().copy()
            v[axis] += d if axis < 3 else np.radians(d)
            rows.append(terms(Pose.from_vector(v)))
        rec[name] = {k: [r[k] for r in rows] for k in at}
        unit = "m" if axis < 3 else "deg"
        cells = []
        for k in at:
            vals = np.array(rec[name][k])
            rise = (vals[1] + vals[5]) / 2 - vals[3]
            cells.append(f"{k} min at {steps[int(np.argmin(vals))]:+g} {unit}, rise "
                         f"{rise:+.4f} ({100 * rise / max(abs(vals[3]), 1e-9):+.1f} %)")
        print(f"{folder.name:26} {name:5} " + "; ".join(cells), flush=True)
    print(f"{folder.name:26} at truth: " + ", ".join(f"{k} {v:.4f}" for k, v in at.items())
          + f" (load {os.getloadavg()[0]:.1f})", flush=True)
    if out is not None:
        with out.open("a") as f:
            f.write(json.dumps(rec) + "\n")


def source_of(scene: str) -> str:
    for prefix, name in (("kitti00_", "KITTI 00 single frames"), ("object_", "KITTI object"),
                         ("pjlab_", "PJLab")):
        if scene.startswith(prefix):
            return name
    return "other"


def table(records: list[dict]) -> str:
    """Per source and setting: runs, median error, worst, how often it beat the first setting
    from the same start (lower translation error), median CPU s per calibration."""
    settings = list(dict.fromkeys(r["setting"] for r in records))
    sources = list(dict.fromkeys(source_of(r["scene"]) for r in records))
    first = {(r["scene"], r["run"]): r for r in records if r["setting"] == settings[0]}
    lines = ["| source | setting | runs | median error | worst | good (of them > 30 cm / 0.5 deg) "
             f"| beats {settings[0]} (same start) | median CPU s | median wall s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for src in sources:
        for s in settings:
            g = [r for r in records if r["setting"] == s and source_of(r["scene"]) == src]
            if not g:
                continue
            t = np.array([r["t_cm"] for r in g])
            a = np.array([r["r_deg"] for r in g])
            good = [r for r in g if r["verdict"] == "good"]
            bad = sum(r["t_cm"] > 30 or r["r_deg"] > 0.5 for r in good)
            pairs = [(r, first[(r["scene"], r["run"])]) for r in g
                     if (r["scene"], r["run"]) in first]
            wins = sum(r["t_cm"] < f["t_cm"] for r, f in pairs)
            lines.append(f"| {src} | {s} | {len(g)} | {np.median(t):.1f} cm / "
                         f"{np.median(a):.2f} deg | {t.max():.0f} cm / {a.max():.2f} deg | "
                         f"{len(good)} ({bad}) | "
                         f"{'-' if s == settings[0] else f'{wins} of {len(pairs)}'} | "
                         f"{np.median([r['cpu'] for r in g]):.1f} | "
                         f"{np.median([r['seconds'] for r in g]):.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="*", type=Path)
    ap.add_argument("--settings", default="lik,lik_e0.1,lik_e0.3")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("cues.jsonl"))
    ap.add_argument("--table", nargs="*", type=Path, help="print the table of these record files")
    ap.add_argument("--cost", type=int, default=0, metavar="N",
                    help="instead: CPU ms per loss evaluation over N poses, per setting")
    ap.add_argument("--profile", action="store_true",
                    help="instead: each term alone around the truth (see the module docstring)")
    args = ap.parse_args(argv)
    if args.profile:
        for folder in args.scenes:
            profile(folder, args.out if args.out != Path("cues.jsonl") else None)
        return 0
    if args.cost:
        for folder in args.scenes:
            cost(folder, args.settings.split(","), args.cost)
        return 0
    if args.table is not None:
        records = [json.loads(line) for p in args.table for line in p.read_text().splitlines()
                   if line.strip()]
        print(table(records))
        return 0
    for folder in args.scenes:
        run_scene(folder, args.settings.split(","), args.runs, args.seed, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
