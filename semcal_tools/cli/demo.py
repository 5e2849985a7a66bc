"""``semcal demo``: the main job on a built-in scene, start to finish, with its error printed.

By default (``make demo``) the roadside demo of issue 13: two cameras of one junction calibrated
against one map by one calibrator, the calibration_monitor watching both, one camera knocked by
0.3 deg / 5 cm and the monitor's WARN with the drift it estimated
(:func:`semcal_tools.live_demo.run_drift_demo`). ``--single``: the single-camera live pipeline
(map_builder, bag replay, the calibrate action); ``--offline``: the engine alone on the files.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "demo", help="calibrate the built-in demo scene and print the result and its error",
        description="Generate the demo scene, start the map_builder and calibrator nodes, replay "
                    "the scene's bag, call the calibrate action from the scene's perturbed "
                    "initial pose and print the transform and its error. --offline: the "
                    "calibration engine alone on the scene's files, without ROS.")
    p.add_argument("--out", help="folder for the scene and results (default: a temporary folder)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--single", action="store_true",
                   help="the single-camera live pipeline (map_builder from the bag, one goal) "
                        "instead of the two-camera drift demo")
    p.add_argument("--offline", action="store_true",
                   help="no ROS: calibrate the scene's map and label image directly")
    p.add_argument("--verification-starts", type=int, metavar="N",
                   help="live demos: verification starts of each goal (-1: the calibrator's "
                        "configured number, the full default procedure; 0: one schedule). "
                        "Default: -1 with --single, 0 in the two-camera demo (under 2 minutes)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.offline:
        return run_offline(args)
    from semcal_tools.live_demo import DemoOptions, DriftDemoOptions, run_drift_demo, run_live

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="semcal-demo-"))
    starts = args.verification_starts
    if args.single:
        return run_live(DemoOptions(out, args.seed, -1 if starts is None else starts))
    return run_drift_demo(DriftDemoOptions(out, args.seed, 0 if starts is None else starts))


def run_offline(args: argparse.Namespace) -> int:
    from semcal_ros.cli import main as semcal

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="semcal-demo-"))
    scene = out / "scene"
    if not (scene / "map.ply").is_file():
        print(f"generating the demo scene in {scene} ...")
        code = semcal(["scene", "--kind", "junction", "--seed", str(args.seed), "--size", "small",
                       "--out", str(scene), "--no-bag", "--force"])
        if code:
            return code
    result = out / "result.yaml"
    print("calibrating from the scene's perturbed initial pose ...")
    code = semcal([
        "calibrate", "--map", str(scene / "map.ply"), "--labels", str(scene / "labels.png"),
        "--camera-info", str(scene / "camera_info.yaml"), "--initial", str(scene / "initial.yaml"),
        "--image", str(scene / "image.png"), "--output", str(result),
        "--overlay", str(out / "overlay.png"), "--loss-curve", str(out / "loss_curve.png"),
        "--seed", str(args.seed)])
    if code:
        return code
    from semcal_ros.io.files import read_pose
    from semcal_ros.engine.pose import rotation_error_deg, translation_error

    truth, initial = read_pose(scene / "ground_truth.yaml"), read_pose(scene / "initial.yaml")
    found = read_pose(result)
    print(f"initial error: {translation_error(initial, truth) * 100:.1f} cm, "
          f"{rotation_error_deg(initial, truth):.2f} deg")
    print(f"result error:  {translation_error(found, truth) * 100:.2f} cm, "
          f"{rotation_error_deg(found, truth):.3f} deg")
    return 0
