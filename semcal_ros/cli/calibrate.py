"""``semcal calibrate``: one calibration from files, the result as a pose YAML.

Three forms: one frame (``--map --labels --camera-info``); one static camera's several label
images (``--labels A.png B.png ...``: fused per pixel, :func:`~semcal_ros.engine.frames.fuse_labels`);
several frames of one rig (``--scene DIR [DIR ...]``: scene folders as ``semcal real-scene``
writes them, each with its own map, labels, camera_info and calibrator.yaml, one pose for all:
:func:`~semcal_ros.engine.calibration.calibrate_frames_and_draw`).

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
        description="Register a labelled lidar map (PLY) to a camera's Cityscapes label image; "
                    "or several frames of one rig (--scene DIR ...) to one pose.")
    p.add_argument("--scene", nargs="+", metavar="DIR",
                   help="scene folders of one rig (as semcal real-scene writes them: map.ply in "
                        "the first scan's lidar frame, labels.png, camera_info.yaml, optional "
                        "calibrator.yaml, probabilities.npz, image.png), calibrated together to "
                        "one pose; each folder's calibrator.yaml applies to its frame on top of "
                        "--config. Replaces --map, --labels, --camera-info, --image")
    p.add_argument("--map", help="map.ply (float x, y, z, ushort label)")
    p.add_argument("--labels", nargs="+", metavar="PNG",
                   help="labels.png (mono8 Cityscapes trainIds); several: label images of one "
                        "camera that did not move, fused per pixel (the class most images give)")
    p.add_argument("--camera-info", help="camera_info.yaml (ROS format)")
    p.add_argument("--initial", required=True, help="initial pose YAML (rotation or rpy_deg)")
    p.add_argument("--output", required=True, help="result pose YAML")
    p.add_argument("--overlay", help="PNG: the map rendered at the result over the image "
                                     "(with several --scene: one per scene, OVERLAY_<folder>.png)")
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
                        "when present, with --scene each folder's; 'none' = not used; not "
                        "used with several --labels)")
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


def _progress_bar(quiet: bool):
    """A progress bar on a terminal, none in logs (tqdm's own rule with disable=None), and the
    callback that feeds it."""
    from tqdm import tqdm

    from semcal_ros.engine.results import Progress

    bar = tqdm(total=None, unit="eval", disable=True if quiet else None, file=sys.stderr,
               dynamic_ncols=True, mininterval=0.5,
               bar_format="{desc}: {n_fmt} evaluations [{elapsed}] {postfix}")

    def progress(p: Progress) -> None:
        bar.set_description_str(p.stage)
        bar.update(p.evaluations - bar.n)
        bar.set_postfix_str(f"best loss {p.best_loss:.5f}")

    return bar, progress


def _base_params(args: argparse.Namespace):
    """``--config`` (or the built-in defaults) with ``--yaw-search``; the output paths and the
    seed checked."""
    from semcal_ros.engine import validation
    from semcal_ros.engine.params import CalibrationParams

    params = CalibrationParams.from_file(args.config)
    if args.yaw_search:
        from dataclasses import replace

        params = replace(params, search=replace(params.search, yaw_search=True))
    validation.check(validation.output_problems(args.output, "--output")
                     + validation.output_problems(args.overlay, "--overlay")
                     + validation.output_problems(args.loss_curve, "--loss-curve"))
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    return params


def _read_labels(paths: list[str], camera) -> "tuple[object, str]":
    """The label image, or several of one static camera fused per pixel; and how it was made."""
    from semcal_ros.engine.frames import fuse_labels
    from semcal_ros.io import files

    images = []
    for path in paths:
        labels = files.read_label_image(path)
        if labels.shape != (camera.height, camera.width):
            which = f" {path}" if len(paths) > 1 else ""
            raise ValueError(f"label image{which} is {labels.shape[1]}x{labels.shape[0]} but "
                             f"camera_info says {camera.width}x{camera.height}")
        images.append(labels)
    if len(images) == 1:
        return images[0], ""
    fused = fuse_labels(images)
    return fused.labels, (f"{len(images)} label images fused per pixel: "
                          f"{fused.agreement * 100:.1f} % of the images agree with the fused "
                          "class on average")


def _run(args: argparse.Namespace) -> int:
    if args.scene:
        given = [name for name, value in (("--map", args.map), ("--labels", args.labels),
                                          ("--camera-info", args.camera_info),
                                          ("--image", args.image)) if value]
        if given:
            raise ValueError(f"--scene takes each frame's files from its folder: drop "
                             f"{', '.join(given)}")
        return _run_scenes(args)
    missing = [name for name, value in (("--map", args.map), ("--labels", args.labels),
                                        ("--camera-info", args.camera_info)) if not value]
    if missing:
        raise ValueError(f"missing {', '.join(missing)} (or give --scene DIR ...)")
    from semcal_ros.engine import validation
    from semcal_ros.io import files, ply
    from semcal_ros.engine.calibration import calibrate_and_draw
    from semcal_ros.engine.labels import LabelMapping

    # everything checkable is checked before the work starts (the same checks as the action)
    params = _base_params(args)
    mapping = LabelMapping.from_yaml(args.label_mapping) if args.label_mapping else LabelMapping()
    camera = files.read_camera_info(args.camera_info)
    validation.check(validation.camera_problems(camera.width, camera.height, camera.k, camera.d),
                     f"{args.camera_info}: ")
    labels, fused = _read_labels(args.labels, camera)
    if fused:
        print(fused)
        if args.probabilities not in (None, "none"):
            raise ValueError("--probabilities belongs to one label image, not to several fused")
    probabilities = None if fused else _probabilities(args.probabilities, args.labels[0],
                                                      labels.shape)
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

    bar, progress = _progress_bar(args.quiet)
    try:  # the calibrator node runs the same function (a degenerate result: CalibrationFailed)
        calibration = calibrate_and_draw(cloud, labels, camera, initial, params, mapping,
                                         probabilities=probabilities, background=rgb,
                                         draw=bool(args.overlay), seed=args.seed,
                                         progress=progress)
    finally:
        bar.close()
    _report(args, calibration, [args.overlay] if args.overlay else [])
    return 0


def _report(args: argparse.Namespace, calibration, overlays: list[str]) -> None:
    """Write the result, print it, and write the loss curve and the overlay picture(s)."""
    from semcal_ros.engine.overlay import loss_curve
    from semcal_ros.io import files

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
        print(f"  {result.quality.classes_line()}")
    print(f"result written to {args.output}")
    if args.loss_curve:
        files.write_rgb_image(args.loss_curve, loss_curve(result.history))
        print(f"loss curve written to {args.loss_curve}")
    for check in calibration.frames:
        print(f"  {check.name}: loss {check.loss:.5f}, agreement {check.agreement * 100:.1f} %, "
              f"coverage {check.coverage * 100:.1f} %")
    if overlays:
        pictures = calibration.overlays or [calibration.overlay]
        if any(p is None for p in pictures):  # the result stands; the picture is a by-product
            raise ValueError(f"overlay not drawn: {calibration.overlay_error}")
        for path, picture in zip(overlays, pictures):
            files.write_rgb_image(path, picture)
            print(f"overlay written to {path}")


def _overlay_paths(overlay: str | None, scenes: list[Path]) -> list[str]:
    """One overlay path per scene: ``--overlay`` itself for one scene, else
    ``<stem>_<folder name><suffix>`` beside it (``_2``, ``_3`` ... when folder names repeat)."""
    if not overlay:
        return []
    if len(scenes) == 1:
        return [overlay]
    base = Path(overlay)
    names = [s.resolve().name or f"scene{k + 1}" for k, s in enumerate(scenes)]
    out = []
    for k, name in enumerate(names):
        tag = name if names.count(name) == 1 else f"{name}_{k + 1}"
        out.append(str(base.with_name(f"{base.stem}_{tag}{base.suffix or '.png'}")))
    return out


def _read_scene(folder: Path, base, args: argparse.Namespace, initial, mapping):
    """One frame from a scene folder, checked as the single-frame form checks its files."""
    from semcal_ros.engine import validation
    from semcal_ros.engine.frames import Frame
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.io import files, ply

    if not folder.is_dir():
        raise ValueError(f"--scene {folder}: not a folder")
    for name in ("map.ply", "labels.png", "camera_info.yaml"):
        if not (folder / name).is_file():
            raise ValueError(f"--scene {folder}: no {name} (a scene folder as semcal real-scene "
                             "writes it)")
    own = folder / "calibrator.yaml"
    params = CalibrationParams.from_file(own, base=base) if own.is_file() else base
    camera = files.read_camera_info(folder / "camera_info.yaml")
    validation.check(validation.camera_problems(camera.width, camera.height, camera.k, camera.d),
                     f"{folder / 'camera_info.yaml'}: ")
    labels, _ = _read_labels([str(folder / "labels.png")], camera)
    probabilities = None if args.probabilities == "none" else \
        _probabilities(None, str(folder / "labels.png"), labels.shape)
    rgb = files.read_rgb_image(folder / "image.png") if (folder / "image.png").is_file() else None
    if rgb is not None and rgb.shape[:2] != labels.shape:
        rgb = None  # the overlay then shows the label colours
    cloud = ply.read_ply(folder / "map.ply")
    finite = cloud.finite()
    if len(finite) < len(cloud):
        raise ValueError(f"{folder / 'map.ply'}: map contains {len(cloud) - len(finite)} NaN or "
                         "infinite points")
    validation.check(validation.reach_problems(initial.translation,
                                               validation.map_bounds(cloud.xyz), params,
                                               f"initial pose {args.initial} in {folder}"))
    return Frame(cloud, labels, camera, params, probabilities, rgb, folder.resolve().name)


def _run_scenes(args: argparse.Namespace) -> int:
    """``--scene DIR [DIR ...]``: the frames of one rig calibrated together to one pose."""
    from semcal_ros.engine import validation
    from semcal_ros.engine.calibration import calibrate_frames_and_draw
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.io import files

    if args.probabilities not in (None, "none"):
        raise ValueError("--scene takes each folder's probabilities.npz: --probabilities may "
                         "only be 'none' there")
    base = _base_params(args)
    mapping = LabelMapping.from_yaml(args.label_mapping) if args.label_mapping else LabelMapping()
    initial = files.read_pose(args.initial)
    validation.check(validation.frame_problems(_pose_frame(args.initial), args.map_frame,
                                               f"initial pose {args.initial}"))
    scenes = [Path(s) for s in args.scene]
    frames = [_read_scene(folder, base, args, initial, mapping) for folder in scenes]
    overlays = _overlay_paths(args.overlay, scenes)
    validation.check([p for path in overlays for p in validation.output_problems(path,
                                                                                 "--overlay")])
    print(f"{len(frames)} frame{'s' * (len(frames) > 1)} of one rig: "
          + ", ".join(f.name for f in frames))
    bar, progress = _progress_bar(args.quiet)
    try:
        calibration = calibrate_frames_and_draw(frames, initial, mapping,
                                                draw=bool(overlays), seed=args.seed,
                                                progress=progress)
    finally:
        bar.close()
    _report(args, calibration, overlays)
    return 0
