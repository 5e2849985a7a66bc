"""Error against the number of frames of one rig calibrated together (issue 32).

The eight KITTI 00 single frames of the shared scene folders (one scan each, geometric point
labels, ESPNetv2 labels by default: ``kitti00_NNNNNN_esp``) share one extrinsic, so any subset of
them is a multi-frame calibration of one rig. For n frames (evenly spread over the drive), from
the paper's starts (truth + uniform +-2.5 m / +-5 deg pitch and yaw,
:func:`semcal_tools.protocol.initial_guesses`), one default calibration each
(:func:`semcal_ros.engine.calibration.calibrate_frames_and_draw`, no overlay): error and seconds.
With one frame, start k uses frame k (mod 8), so the single-frame row is spread over frames too.

Resumable pieces: each run is one line of JSON in ``--out`` (skipped when already there), so a
study is split into jobs under the shared lock, each well below 10 min::

    python benchmarks/multiframe_study.py run --scenes SCENES --frames 8 \\
        --starts 0 1 --loss l2 --out /tmp/mf.jsonl
    python benchmarks/multiframe_study.py table /tmp/mf.jsonl

Static camera (``static``): a catalogue layout from ``semcal scene`` (its map, camera and truth),
ten label images of its camera, each at another moment of the traffic and with fresh
network-like noise (:func:`static_images`), fused per pixel, calibrated from the paper's starts
(``--modes single`` for the first image alone, the comparison).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

FRAMES = ("000556", "001112", "001668", "002224", "002780", "003336", "003892", "004448")


def load_frame(folder: Path, base):
    """One scene folder as a :class:`Frame`, as ``semcal calibrate --scene`` reads it."""
    from semcal_ros.engine.frames import Frame
    from semcal_ros.engine.loss import read_probabilities
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.io import files, ply

    own = folder / "calibrator.yaml"
    params = CalibrationParams.from_file(own, base=base) if own.is_file() else base
    probs = folder / "probabilities.npz"
    return Frame(ply.read_ply(folder / "map.ply"), files.read_label_image(folder / "labels.png"),
                 files.read_camera_info(folder / "camera_info.yaml"), params,
                 read_probabilities(probs) if probs.is_file() else None, None, folder.name)


def subset(n: int, start: int) -> list[str]:
    """The n frames of a run: evenly spread over the drive; one frame: frame ``start`` mod 8."""
    if n == 1:
        return [FRAMES[start % len(FRAMES)]]
    return [FRAMES[int(i)] for i in np.round(np.linspace(0, len(FRAMES) - 1, n))]


def paper_starts(indices: list[int]):
    """The protocol's ProtocolParams for the paper's starts: 30 (or more) drawn, the first ones
    used, so start k is the same whichever others a job runs."""
    from semcal_tools.protocol import ProtocolParams

    return ProtocolParams(runs=max(30, max(indices) + 1), keep=1, seed=0)


def engine_commit() -> str:
    """The commit of the code this run uses (the worktree's HEAD, + when it has changes)."""
    import subprocess

    here = Path(__file__).resolve().parent
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True,
                          text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "semcal_ros"], cwd=here.parent,
                           capture_output=True, text=True).stdout.strip()
    return head + ("+" if dirty else "")


def load_avg() -> float:
    return os.getloadavg()[0]


def done_keys(out: Path) -> set[tuple]:
    if not out.is_file():
        return set()
    keys = set()
    for line in out.read_text().splitlines():
        r = json.loads(line)
        keys.add((r["kind"], r["frames"], r["loss"], r["start"], r.get("suffix", "esp")))
    return keys


def run(args: argparse.Namespace) -> None:
    from semcal_ros.engine.calibration import calibrate_frames_and_draw
    from semcal_ros.engine.loss import LossParams
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.errors import CalibrationFailed
    from semcal_ros.io import files
    from semcal_tools.protocol import initial_guesses

    base = CalibrationParams.from_file(args.config)
    base = replace(base, loss=replace(base.loss, kind=args.loss))
    LossParams(kind=args.loss)  # an unknown kind: the engine's own message
    out = Path(args.out)
    have = done_keys(out)
    for n in args.frames:
        for k in args.starts:
            key = ("rig", n, args.loss, k, args.suffix)
            if key in have:
                continue
            names = subset(n, k)
            folders = [Path(args.scenes) / f"kitti00_{name}_{args.suffix}" for name in names]
            truth = files.read_pose(folders[0] / "ground_truth.yaml")
            starts = initial_guesses(truth, paper_starts(args.starts))
            frames = [load_frame(f, base) for f in folders]
            load0 = load_avg()
            t0 = time.perf_counter()
            c0 = time.process_time()
            row = {"kind": "rig", "frames": n, "loss": args.loss, "start": k,
                   "suffix": args.suffix, "names": names, "engine": engine_commit()}
            try:
                cal = calibrate_frames_and_draw(frames, starts[k], draw=False, seed=0)
                res = cal.result
                row.update(
                    translation_cm=round(translation_error(res.pose, truth) * 100, 2),
                    rotation_deg=round(rotation_error_deg(res.pose, truth), 4),
                    verdict=res.quality.verdict if res.quality else "",
                    reason=res.quality.reason if res.quality else "",
                    uncertainty=([*res.quality.uncertainty_translation_m,
                                  *res.quality.uncertainty_rpy_deg] if res.quality else None),
                    loss_value=round(res.loss, 6), evaluations=res.evaluations,
                    agreement=[round(c.agreement, 3) for c in cal.frames])
            except CalibrationFailed as exc:
                row.update(error=str(exc), translation_cm=None, rotation_deg=None)
            row.update(seconds=round(time.perf_counter() - t0, 2),
                       cpu_seconds=round(time.process_time() - c0, 2),
                       load=[round(load0, 2), round(load_avg(), 2)])
            print(json.dumps(row), flush=True)
            with out.open("a") as fh:
                fh.write(json.dumps(row) + "\n")


def static_images(folder: Path, count: int, noise: str, spacing_s: float) -> list[np.ndarray]:
    """``count`` label images of a catalogue scene's camera (``semcal scene --size full --frame
    random --mast bracket``), each at another moment of its
    traffic (the ``dynamic`` variant's 9 cars and 12 people, ``spacing_s`` apart) and each with
    fresh network-like noise (:func:`semcal_tools.scenes.labelnoise.noisy_labels` ``noise``)."""
    import yaml

    from semcal_ros.engine.pose import Pose
    from semcal_ros.io import files
    from semcal_tools.scenes import SIZES
    from semcal_tools.scenes.actors import actors_at
    from semcal_tools.scenes.generate import camera_images, scene_world
    from semcal_tools.scenes.labelnoise import noisy_labels

    meta = yaml.safe_load((folder / "scene.yaml").read_text())
    options = replace(SIZES["full"], map_frame="random", mast="bracket", supersample=1)
    sw = scene_world(meta["kind"], int(meta["seed"]), "dynamic", options)
    pose = files.read_pose(folder / "ground_truth.yaml")
    rot = sw.frame.rotation
    layout_pose = Pose.from_matrix(rot.T @ pose.rotation,
                                   rot.T @ (pose.translation - np.asarray(sw.frame.shift)))
    out = []
    for k in range(count):
        t = sw.t_camera + spacing_s * k
        labels, _ = camera_images(sw.world, layout_pose, actors_at(sw.image_actors, t), options,
                                  False, np.random.default_rng(k), np.random.default_rng(0),
                                  rgb=False)
        out.append(noisy_labels(labels, noise, seed=1000 + k))
    return out


def static(args: argparse.Namespace) -> None:
    """A static camera: ten noisy label images of a catalogue layout, fused, calibrated."""
    from semcal_ros.engine.calibration import calibrate_and_draw
    from semcal_ros.engine.frames import fuse_labels
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.pose import rotation_error_deg, translation_error
    from semcal_ros.io import files, ply
    from semcal_tools.protocol import initial_guesses

    out = Path(args.out)
    have = done_keys(out)
    folder = Path(args.scene)
    truth = files.read_pose(folder / "ground_truth.yaml")
    camera = files.read_camera_info(folder / "camera_info.yaml")
    cloud = ply.read_ply(folder / "map.ply")
    own = folder / "calibrator.yaml"
    params = CalibrationParams.from_file(own) if own.is_file() else CalibrationParams()
    params = replace(params, loss=replace(params.loss, kind=args.loss))
    images = static_images(folder, args.images, args.noise, args.spacing)
    t0 = time.thread_time()
    fused = fuse_labels(images)
    fuse_s = time.thread_time() - t0
    starts = initial_guesses(truth, paper_starts(args.starts))
    for mode in args.modes:
        target = fused.labels if mode == "fused" else images[0]
        for k in args.starts:
            key = (f"static-{mode}", args.images, args.loss, k, folder.name)
            if key in have:
                continue
            load0 = load_avg()
            t1 = time.perf_counter()
            cal = calibrate_and_draw(cloud, target, camera, starts[k], params, draw=False,
                                     seed=0)
            res = cal.result
            row = {"kind": f"static-{mode}", "frames": args.images, "loss": args.loss,
                   "start": k, "suffix": folder.name, "noise": args.noise,
                   "engine": engine_commit(),
                   "translation_cm": round(translation_error(res.pose, truth) * 100, 2),
                   "rotation_deg": round(rotation_error_deg(res.pose, truth), 4),
                   "verdict": res.quality.verdict if res.quality else "",
                   "fuse_cpu_seconds": round(fuse_s, 3), "agreement": round(fused.agreement, 3),
                   "seconds": round(time.perf_counter() - t1, 2),
                   "load": [round(load0, 2), round(load_avg(), 2)]}
            print(json.dumps(row), flush=True)
            with out.open("a") as fh:
                fh.write(json.dumps(row) + "\n")


def table(args: argparse.Namespace) -> None:
    rows = [json.loads(line) for p in args.files for line in Path(p).read_text().splitlines()]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["kind"], r["suffix"], r["loss"], r["frames"]), []).append(r)
    print("| kind | labels | loss | frames | runs | median cm / deg | worst cm / deg | "
          "<= 3 cm & 0.1 deg | s per run (median) | load |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for key in sorted(groups):
        g = groups[key]
        ok = [r for r in g if r.get("translation_cm") is not None]
        t = np.array([r["translation_cm"] for r in ok])
        a = np.array([r["rotation_deg"] for r in ok])
        s = np.array([r["seconds"] for r in g])
        loads = [x for r in g for x in r["load"]]
        hits = int(np.sum((t <= 3.0) & (a <= 0.1))) if len(ok) else 0
        print(f"| {key[0]} | {key[1]} | {key[2]} | {key[3]} | {len(g)} | "
              + (f"{np.median(t):.1f} / {np.median(a):.3f} | {t.max():.1f} / {a.max():.3f}"
                 if len(ok) else "- | -")
              + f" | {hits}/{len(g)} | {np.median(s):.1f} | {min(loads):.1f}-{max(loads):.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--frames", type=int, nargs="+", default=[8])
    r.add_argument("--starts", type=int, nargs="+", default=[0, 1, 2])
    r.add_argument("--loss", default="l2")
    r.add_argument("--suffix", default="esp", help="label source of the scene folders")
    r.add_argument("--scenes", required=True,
                   help="folder holding kitti00_NNNNNN_SUFFIX scene folders (semcal real-scene)")
    r.add_argument("--config", help="engine parameters under each folder's (default: defaults)")
    r.add_argument("--out", required=True)
    r.set_defaults(func=run)
    s = sub.add_parser("static")
    s.add_argument("--scene", required=True, help="a catalogue scene folder (semcal scene)")
    s.add_argument("--images", type=int, default=10)
    s.add_argument("--starts", type=int, nargs="+", default=list(range(6)))
    s.add_argument("--modes", nargs="+", default=["fused"], choices=["fused", "single"])
    s.add_argument("--loss", default="l2")
    s.add_argument("--noise", default="network", help="labelnoise model (network, kitti_espnetv2)")
    s.add_argument("--spacing", type=float, default=3.0, help="s between the label images")
    s.add_argument("--out", required=True)
    s.set_defaults(func=static)
    t = sub.add_parser("table")
    t.add_argument("files", nargs="+")
    t.set_defaults(func=table)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
