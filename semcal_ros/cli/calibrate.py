"""``semcal calibrate``: one calibration from files, the result as a pose YAML.

Every input is checked before the (minutes long) work starts, with the checks the ``calibrate``
action uses (:mod:`semcal_ros.engine.validation`): parameters named, output folders writable, frames
matching, the initial pose near the map; a degenerate best pose is an error, never a result.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


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
    p.add_argument("--map-frame", default="map",
                   help="frame of the map; the initial pose's frame_id must match (default: map)")
    p.add_argument("--probabilities",
                   help="the segmenter's class probabilities (.npz, key 'probabilities', "
                        "(H, W, 19) softmax over Cityscapes trainIds): the loss takes the "
                        "expected cost under them (default: probabilities.npz beside --labels "
                        "when present; 'none' = not used)")
    p.add_argument("--seed", type=int, default=0, help="seed of the verification starts")
    p.add_argument("--yaw-search", action="store_true",
                   help="heading unknown: search the yaw over the full circle first "
                        "(engine.search.yaw_search; docs/engine.md: how good must the start be)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _pose_frame(path: str) -> str | None:
    """The ``frame_id`` a pose YAML declares (None: none; the map frame is then assumed)."""
    import yaml

    data = yaml.safe_load(Path(path).read_text())
    frame = data.get("frame_id") if isinstance(data, dict) else None
    return str(frame) if frame is not None else None


def _probabilities(given: str | None, labels_path: str, shape: tuple[int, int]):
    """The class probabilities to use: ``--probabilities``, else ``probabilities.npz`` beside the
    label image when there is one (what ``semcal real-scene --probabilities`` writes)."""
    from semcal_ros.engine.loss import read_probabilities

    if given == "none":
        return None
    path = Path(given) if given else Path(labels_path).parent / "probabilities.npz"
    if not path.is_file():
        if given:
            raise ValueError(f"--probabilities: no such file: {given}")
        return None
    probabilities = read_probabilities(path)
    if probabilities.shape[:2] != shape:
        raise ValueError(f"{path}: probabilities are {probabilities.shape[1]}x"
                         f"{probabilities.shape[0]} but the label image is {shape[1]}x{shape[0]}")
    print(f"class probabilities from {path}")
    return probabilities


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except ValueError as exc:  # some library messages span lines (YAML parser errors)
        raise ValueError(" ".join(str(exc).split())) from None


def _run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from semcal_ros.engine import validation
    from semcal_ros.io import files, ply
    from semcal_ros.engine.calibration import calibrate_and_draw
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.engine.overlay import loss_curve
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.results import Progress

    # everything checkable is checked before the work starts (the same checks as the action)
    params = CalibrationParams.from_file(args.config)
    if args.yaw_search:
        from dataclasses import replace

        params = replace(params, search=replace(params.search, yaw_search=True))
    validation.check(validation.output_problems(args.output, "--output")
                     + validation.output_problems(args.overlay, "--overlay")
                     + validation.output_problems(args.loss_curve, "--loss-curve"))
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    mapping = LabelMapping.from_yaml(args.label_mapping) if args.label_mapping else LabelMapping()
    camera = files.read_camera_info(args.camera_info)
    validation.check(validation.camera_problems(camera.width, camera.height, camera.k, camera.d),
                     f"{args.camera_info}: ")
    labels = files.read_label_image(args.labels)
    if labels.shape != (camera.height, camera.width):
        raise ValueError(f"label image is {labels.shape[1]}x{labels.shape[0]} but camera_info "
                         f"says {camera.width}x{camera.height}")
    probabilities = _probabilities(args.probabilities, args.labels, labels.shape)
    initial = files.read_pose(args.initial)
    validation.check(validation.frame_problems(_pose_frame(args.initial), args.map_frame,
                                               f"initial pose {args.initial}"))
    rgb = files.read_rgb_image(args.image) if args.image else None
    if rgb is not None and rgb.shape[:2] != labels.shape:
        raise ValueError(f"--image is {rgb.shape[1]}x{rgb.shape[0]} but the label image is "
                         f"{labels.shape[1]}x{labels.shape[0]}")
    cloud = ply.read_ply(args.map)
    finite = cloud.finite()
    if len(finite) < len(cloud):
        raise ValueError(f"{args.map}: map contains {len(cloud) - len(finite)} NaN or infinite "
                         f"points")
    validation.check(validation.reach_problems(initial.translation,
                                               validation.map_bounds(cloud.xyz), params,
                                               f"initial pose {args.initial}"))

    # disable=None: a bar on a terminal, none in logs (tqdm's own rule)
    bar = tqdm(total=None, unit="eval", disable=True if args.quiet else None, file=sys.stderr,
               dynamic_ncols=True, mininterval=0.5,
               bar_format="{desc}: {n_fmt} evaluations [{elapsed}] {postfix}")

    def progress(p: Progress) -> None:
        bar.set_description_str(p.stage)
        bar.update(p.evaluations - bar.n)
        bar.set_postfix_str(f"best loss {p.best_loss:.5f}")

    try:  # the calibrator node runs the same function (a degenerate result: CalibrationFailed)
        calibration = calibrate_and_draw(cloud, labels, camera, initial, params, mapping,
                                         probabilities=probabilities, background=rgb,
                                         draw=bool(args.overlay), seed=args.seed,
                                         progress=progress)
    finally:
        bar.close()
    result = calibration.result
    files.write_pose(args.output, result.pose, result.to_dict())
    rpy = result.pose.body_rpy_deg()
    t = result.pose.translation
    print(f"translation [m]: {t[0]:.4f} {t[1]:.4f} {t[2]:.4f}")
    print(f"rpy [deg]:       {rpy[0]:.4f} {rpy[1]:.4f} {rpy[2]:.4f}")
    print(f"loss {result.loss:.6f}, {result.evaluations} evaluations, {result.seconds:.1f} s; "
          f"{result.accepted}/{len(result.runs)} runs accepted, spread "
          f"{result.spread_translation_m * 100:.1f} cm / {result.spread_rotation_deg:.3f} deg")
    if result.quality is not None:
        print(f"quality {result.quality.summary()}")
    print(f"result written to {args.output}")
    if args.loss_curve:
        files.write_rgb_image(args.loss_curve, loss_curve(result.history))
        print(f"loss curve written to {args.loss_curve}")
    if args.overlay:
        if calibration.overlay is None:  # the result stands; the picture is a by-product
            raise ValueError(f"overlay not drawn: {calibration.overlay_error}")
        files.write_rgb_image(args.overlay, calibration.overlay)
        print(f"overlay written to {args.overlay}")
    return 0
