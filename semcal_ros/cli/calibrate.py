"""``semcal calibrate``: one calibration from files, the result as a pose YAML."""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate", help="find the camera pose from a labelled map and a label image",
        description="Register a labelled lidar map (PLY) to a camera's Cityscapes label image.")
    p.add_argument("--map", required=True, help="map.ply (float x, y, z, ushort label)")
    p.add_argument("--labels", required=True, help="labels.png (mono8 Cityscapes trainIds)")
    p.add_argument("--camera-info", required=True, help="camera_info.yaml (ROS format)")
    p.add_argument("--initial", required=True, help="initial pose YAML (rotation or rpy_deg)")
    p.add_argument("--output", required=True, help="result pose YAML")
    p.add_argument("--overlay", help="PNG: the map rendered at the result over the image")
    p.add_argument("--image", help="RGB camera image for the overlay (default: the label colours)")
    p.add_argument("--loss-curve", help="PNG: loss per evaluation")
    p.add_argument("--config", help="ROS 2 parameter file (default: built-in defaults, "
                                    "as config/calibrator.yaml)")
    p.add_argument("--label-mapping", help="YAML changing the class alignment")
    p.add_argument("--seed", type=int, default=0, help="seed of the verification starts")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from semcal_ros.engine_config import load_calibration_params
    from semcal_ros.io import files, ply
    from semcal_ros.labels import LabelMapping, colorize
    from semcal_ros.optimize import Progress, calibrate
    from semcal_ros.overlay import loss_curve, render_overlay

    params = load_calibration_params(args.config)
    mapping = LabelMapping.from_yaml(args.label_mapping) if args.label_mapping else LabelMapping()
    camera = files.read_camera_info(args.camera_info)
    labels = files.read_label_image(args.labels)
    initial = files.read_pose(args.initial)
    cloud = ply.read_ply(args.map)
    rgb = files.read_rgb_image(args.image) if args.image else None
    if rgb is not None and rgb.shape[:2] != labels.shape:
        raise ValueError(f"--image is {rgb.shape[1]}x{rgb.shape[0]} but the label image is "
                         f"{labels.shape[1]}x{labels.shape[0]}")

    # disable=None: a bar on a terminal, none in logs (tqdm's own rule)
    bar = tqdm(total=None, unit="eval", disable=True if args.quiet else None, file=sys.stderr,
               dynamic_ncols=True, mininterval=0.5,
               bar_format="{desc}: {n_fmt} evaluations [{elapsed}] {postfix}")

    def progress(p: Progress) -> None:
        bar.set_description_str(p.stage)
        bar.update(p.evaluations - bar.n)
        bar.set_postfix_str(f"best loss {p.best_loss:.5f}")

    try:
        result = calibrate(cloud, labels, camera, initial, params, mapping, args.seed, progress)
    finally:
        bar.close()
    files.write_pose(args.output, result.pose, result.to_dict())
    rpy = result.pose.body_rpy_deg()
    t = result.pose.translation
    print(f"translation [m]: {t[0]:.4f} {t[1]:.4f} {t[2]:.4f}")
    print(f"rpy [deg]:       {rpy[0]:.4f} {rpy[1]:.4f} {rpy[2]:.4f}")
    print(f"loss {result.loss:.6f}, {result.evaluations} evaluations, {result.seconds:.1f} s; "
          f"{result.accepted}/{len(result.runs)} runs accepted, spread "
          f"{result.spread_translation_m * 100:.1f} cm / {result.spread_rotation_deg:.3f} deg")
    print(f"result written to {args.output}")
    if args.overlay:
        background = rgb if rgb is not None else colorize(labels)
        files.write_rgb_image(args.overlay, render_overlay(
            cloud, camera, result.pose, background, mapping, params.render))
        print(f"overlay written to {args.overlay}")
    if args.loss_curve:
        files.write_rgb_image(args.loss_curve, loss_curve(result.history))
        print(f"loss curve written to {args.loss_curve}")
    return 0
